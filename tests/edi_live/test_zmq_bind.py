"""Publishing on an IPv6 loopback endpoint, and refusing an ipc:// path another live process serves; a plain
libzmq SUB socket and a plain Unix socket are the independent peers."""

from __future__ import annotations

import socket
import time

import pytest
import zmq

from edi_live import wire
from edi_live.errors import BindError
from edi_live.publisher import Publisher
from tests.edi_live.test_publisher import make_rec


def has_ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.fixture
def started():
    made = []

    def start(endpoints):
        pub = Publisher(endpoints, "cam")
        made.append(pub)
        pub.start()
        return pub

    yield start
    for pub in made:
        pub.close()


@pytest.mark.skipif(not has_ipv6_loopback(), reason="this machine has no IPv6 loopback")
def test_an_ipv6_loopback_endpoint_is_bound_and_serves_a_subscriber(started):
    pub = started(["tcp://[::1]:*"])
    (endpoint,) = pub.bound_endpoints
    assert endpoint.startswith("tcp://[::1]:")
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    try:
        sub.setsockopt(zmq.IPV6, 1)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(endpoint)
        deadline = time.monotonic() + 10
        while not sub.poll(20):  # frames sent before the subscription arrives are not sent: submit until one is
            assert time.monotonic() < deadline, "no frame arrived over IPv6"
            pub.submit(make_rec(3))
        assert sub.recv_multipart()[0] == wire.FRAME_TOPIC
    finally:
        sub.close(linger=0)
        ctx.term()


def test_an_ipv4_endpoint_is_still_reported_as_the_ipv4_address(started):
    pub = started(["tcp://127.0.0.1:*"])
    assert pub.bound_endpoints[0].startswith("tcp://127.0.0.1:")  # not tcp://[::ffff:127.0.0.1]:


def test_an_ipc_path_another_process_serves_is_refused_not_taken_over(tmp_path):
    path = tmp_path / "frames.sock"
    holder = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    holder.bind(str(path))
    holder.listen(1)  # as a running edi-live's ipc endpoint would
    try:
        pub = Publisher([f"ipc://{path}"], "cam")
        with pytest.raises(BindError, match="another process") as info:
            pub.start()
        assert str(path) in str(info.value) and "\n" not in str(info.value)
        pub.close()
        holder.getsockname()  # still its own: the path was not unlinked and bound again
        assert path.is_socket()
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.connect(str(path))  # the first process still answers there
        probe.close()
    finally:
        holder.close()


def test_an_ipc_path_left_by_a_killed_process_is_reused(tmp_path, started):
    path = tmp_path / "frames.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))  # bound, then closed without unlinking: what a SIGKILLed node leaves
    stale.close()
    assert path.is_socket()
    pub = started([f"ipc://{path}"])
    assert pub.bound_endpoints == [f"ipc://{path}"]
