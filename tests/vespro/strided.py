"""Test helper: an initialiser called on every ``stride``-th frame only."""


class Strided:
    """The initialiser ``ini`` called only on frames whose index is a multiple of ``stride``
    (as the server's worker calls it, a call taking several frame periods), with the
    initialiser's hand-over hooks (``reseed``, ``await_confirmation``, ...) passed through to
    the tracker."""

    def __init__(self, ini, stride: int = 5):
        self.ini, self.stride = ini, stride

    def __call__(self, fs):
        return None if fs.index % self.stride else self.ini(fs)

    def __getattr__(self, name):
        return getattr(self.ini, name)
