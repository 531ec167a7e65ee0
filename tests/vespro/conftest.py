import pytest


class KeptMessages:
    """A publisher for a pose server under test: keeps every message it is given."""

    def __init__(self):
        self.msgs = []

    def publish(self, msg):
        self.msgs.append(msg)

    def stats(self):
        from vespro.link import LinkStats

        return LinkStats(len(self.msgs), len(self.msgs), 0, 0, 1, 1, 0, 0, ())


@pytest.fixture
def kept_publisher() -> KeptMessages:
    """A publisher that keeps what the server publishes (``.msgs``)."""
    return KeptMessages()
