"""Fixtures of the sharing tests."""

import pytest
from sharing_support import service


@pytest.fixture
def server():
    """make(**transport) -> a started SharingService of vehicle 1 on loopback; all stopped after."""
    started = []

    def make(*args, **kwargs):
        svc = service(1, *args, **kwargs).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()
