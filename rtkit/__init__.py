"""What both sides' processes share: a worker process fed by a bounded queue, named shared-memory blocks.

Below ``vespro`` and ``servo``: both may import it; it imports neither (nor ``cellsim``).

- ``logproc``: a worker in a process of its own fed by a bounded queue (both sides' Rerun views).
- ``shm``: ``SharedBlock``, a named block of float64 words in shared memory.
"""
