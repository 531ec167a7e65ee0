"""VESPRO: vision-based 6-DoF pose estimation for robot cells.

Data flows one way: capture -> model/visibility -> tracker -> server -> link -> servo.
"""

__version__ = "0.1.0"
