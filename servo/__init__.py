"""VESPRO control side: 500 Hz position-based visual servoing.

Imports from ``vespro`` only the wire protocol module (``vespro.wire``).
"""

__version__ = "0.1.0"
