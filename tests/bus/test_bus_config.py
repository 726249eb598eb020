"""Bus configuration details that python-can leaves to the caller."""


def test_socketcan_receive_queue_is_enlarged():
    """A SocketCAN bus asks for a multi-second receive queue: as root (CAP_NET_ADMIN) the full
    size, otherwise as much as ``net.core.rmem_max`` allows. Checked on a real socket."""
    import os
    import socket

    from thermal_edge.bus.busconfig import RECEIVE_QUEUE_BYTES, enlarge_receive_queue

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        enlarge_receive_queue(sock)
        after = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)  # Linux reports twice the request
    rmem_max = int(open("/proc/sys/net/core/rmem_max").read())
    want = RECEIVE_QUEUE_BYTES if os.geteuid() == 0 else min(RECEIVE_QUEUE_BYTES, rmem_max)
    assert after >= want > 0, (before, after, want)
