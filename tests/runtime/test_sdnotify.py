"""sd_notify messages reach a NOTIFY_SOCKET the way systemd reads them."""

import socket

import pytest

from runtime.service.sdnotify import SystemdNotifier


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(1.0)
    yield str(path), sock
    sock.close()


def _drain(sock):
    messages = []
    sock.settimeout(0.05)
    try:
        while True:
            messages.append(sock.recv(4096).decode())
    except (socket.timeout, BlockingIOError):
        return messages


def test_ready_status_watchdog_stopping(notify_socket):
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert notifier.enabled and notifier.ping_interval_s == 1.0
    notifier.ready("waiting for offboard")
    assert sock.recv(4096).decode() == "READY=1\nSTATUS=waiting for offboard"
    notifier.loop_alive(now_s=10.0)
    notifier.loop_alive(now_s=10.5)  # within half the period: no second ping
    notifier.loop_alive(now_s=11.0)
    notifier.status("flying")
    notifier.stopping()
    assert _drain(sock) == ["WATCHDOG=1", "WATCHDOG=1", "STATUS=flying", "STOPPING=1"]
    notifier.close()


def test_no_watchdog_configured_sends_no_pings(notify_socket):
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path})
    notifier.loop_alive(now_s=1.0)
    assert _drain(sock) == []


def test_outside_systemd_is_a_no_op():
    notifier = SystemdNotifier({})
    assert not notifier.enabled
    notifier.ready()
    notifier.loop_alive()
