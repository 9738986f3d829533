"""The subscriber callbacks: the guard against internal targets, and delivery with retries to a
real HTTP server on 127.0.0.1."""

from __future__ import annotations

import ipaddress
from collections.abc import Iterator

import pytest

from lidar_outliers.jobs.callbacks import (
    CallbackRefused,
    check_target,
    deliver,
    is_public,
    parse_subscriber,
)
from tests.receiver import Receiver


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver(fail_first=2)
    yield server
    server.close()


@pytest.mark.parametrize("address", [
    "127.0.0.1", "10.1.2.3", "172.16.0.1", "192.168.1.1", "169.254.169.254", "100.64.0.1",
    "0.0.0.0", "240.0.0.1", "224.0.0.1", "255.255.255.255", "::1", "fe80::1", "fc00::1", "::",
    "::ffff:127.0.0.1", "::ffff:10.0.0.1", "2001:db8::1",
])
def test_internal_addresses_are_not_public(address: str) -> None:
    assert not is_public(ipaddress.ip_address(address))


@pytest.mark.parametrize("address", ["8.8.8.8", "1.1.1.1", "2606:4700:4700::1111"])
def test_internet_addresses_are_public(address: str) -> None:
    assert is_public(ipaddress.ip_address(address))


@pytest.mark.parametrize("url", [
    "http://127.0.0.1:9/x", "http://localhost/x", "http://[::1]/x", "http://169.254.169.254/",
    "http://10.0.0.7/hook", "http://[::ffff:192.168.0.1]/", "http://0x7f000001/",
    "ftp://8.8.8.8/", "http://user:pw@8.8.8.8/", "file:///etc/passwd", "http:///nohost",
])
def test_the_guard_refuses_internal_and_odd_targets(url: str) -> None:
    with pytest.raises(CallbackRefused):
        check_target(url, [])


def test_the_guard_resolves_names_and_checks_every_address() -> None:
    # "localhost" is a name: refused for what it resolves to, allowed only when listed
    with pytest.raises(CallbackRefused, match="resolves to"):
        check_target("http://localhost:8080/done", ["127.0.0.1"])
    assert check_target("http://LOCALHOST:8080/done", ["localhost"]) == []
    assert check_target("https://8.8.8.8/hook", []) == [ipaddress.ip_address("8.8.8.8")]


def test_subscriber_names_the_refused_key() -> None:
    with pytest.raises(CallbackRefused, match=r"^subscriber\.failedUri"):
        parse_subscriber({"successUri": "https://8.8.8.8/ok",
                          "failedUri": "http://10.0.0.1/"}, [])
    with pytest.raises(CallbackRefused, match="unknown"):
        parse_subscriber({"doneUri": "https://8.8.8.8/"}, [])
    assert parse_subscriber({"inProgressUri": "https://8.8.8.8/p"}, []) == {
        "inProgressUri": "https://8.8.8.8/p"}


def test_delivery_is_retried_with_backoff_until_accepted(receiver: Receiver) -> None:
    delays: list[float] = []
    assert deliver(receiver.url + "/done", {"jobID": "j1"}, ["127.0.0.1"], attempts=3,
                   sleep=delays.append)
    assert receiver.posts("/done") == [{"jobID": "j1"}] * 3  # 503, 503, then 200
    assert delays == [1.0, 2.0]


def test_delivery_gives_up_after_the_last_attempt(receiver: Receiver) -> None:
    delays: list[float] = []
    assert not deliver(receiver.url + "/done", {"n": 1}, ["127.0.0.1"], attempts=2,
                       sleep=delays.append)
    assert len(receiver.posts("/done")) == 2 and delays == [1.0]


def test_delivery_checks_the_target_again_at_call_time(receiver: Receiver) -> None:
    # a target accepted at submission (say, before its name was re-pointed) is checked again
    assert not deliver(receiver.url + "/done", {"n": 1}, [], sleep=lambda _: None)
    assert receiver.received == []
