"""Reaching a Ray cluster, and telling a lost task from a failed design.

Ray's own `ray.init(address=...)` retries a wrong address for minutes (in C++: a signal cannot
interrupt it) and, when the cluster uses token authentication and this process has no token,
retries forever. So `connect` first opens a plain TCP connection to the address (refused or
silent: a connection error at once, naming the address and the fix), then runs `ray.init` in a
helper thread and gives up after the stated time. Both end in ClusterUnreachable, a
ConnectionError the CLI reports with its own exit status (not the file-error one).

A task whose worker process or node died (a lost node, the memory monitor's kill) says nothing
about its design: `classify` calls that "lost", to be run again a bounded number of times;
anything the design job itself raised is "failed", with its message.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any, Literal

from aperture_fab.errors import Unreachable

__all__ = ["ClusterUnreachable", "Address", "parse_address", "probe", "connect", "classify",
           "Fault", "DEFAULT_CONNECT_TIMEOUT_S", "AUTH_HINT"]

Fault = Literal["lost", "failed"]
#: How long `connect` waits for a cluster by default (--connect-timeout).
DEFAULT_CONNECT_TIMEOUT_S = 30.0
#: The longest single TCP attempt: a silent (filtered) host is tried again until the deadline.
PROBE_ATTEMPT_S = 5.0
#: Pause between TCP attempts to a host that refuses (a head node still starting).
PROBE_PAUSE_S = 0.5
#: Ray's ports when an address has none: the GCS, and the Ray client server (ray://).
GCS_PORT = 6379
CLIENT_PORT = 10001
CLIENT_SCHEME = "ray://"
AUTH_HINT = (
    "if the cluster uses token authentication (Ray's default for clusters started by "
    "`ray start` with RAY_AUTH_MODE=token), run this command with RAY_AUTH_MODE=token and the "
    "cluster's token in RAY_AUTH_TOKEN, in a file named by RAY_AUTH_TOKEN_PATH, or in "
    "~/.ray/auth_token (`ray get-auth-token` on the head node prints it)")
#: Ray's errors that mean the task's process or node went away: the design is not to blame.
LOST_ERRORS = frozenset({
    "WorkerCrashedError", "NodeDiedError", "LocalRayletDiedError", "ObjectLostError",
    "OwnerDiedError", "ObjectFetchTimedOutError", "ObjectReconstructionFailedError",
    "ReferenceCountingAssertionError", "OutOfMemoryError", "RaySystemError",
    "ActorDiedError", "ActorUnavailableError", "NodeDiedException",
})


class ClusterUnreachable(Unreachable, ConnectionError):
    """The Ray cluster at --address could not be reached (or refused this process) in time."""


@dataclass(frozen=True)
class Address:
    """A parsed --address: the text as given, and the host and port to probe (None for
    "auto": this node's cluster, found by Ray from its own files)."""

    text: str
    host: str | None
    port: int | None

    @property
    def client(self) -> bool:
        return self.text.startswith(CLIENT_SCHEME)


def parse_address(text: str) -> Address:
    """'auto', HOST[:PORT] or ray://HOST[:PORT]; raises ValueError naming the value."""
    if text == "auto":
        return Address(text, None, None)
    rest = text.removeprefix(CLIENT_SCHEME)
    host, colon, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
    default = CLIENT_PORT if text.startswith(CLIENT_SCHEME) else GCS_PORT
    if not colon:
        host, port = rest, str(default)
    host = host.strip("[]")  # [::1]:6379
    if not host or "/" in host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address {text!r}: not a Ray address; give auto (this node's "
                         "cluster), HOST:PORT (the head node's GCS, port 6379 by default) or "
                         "ray://HOST:PORT (the Ray client, port 10001 by default).")
    return Address(text, host, int(port))


def _fix(address: Address) -> str:
    where = "the head node" if address.host is None else f"{address.host}"
    port = f"port {address.port}" if address.port is not None else "its port"
    return (f"check that `ray start --head` runs on {where} and listens on {port} (`ray status` "
            "there prints the address), that this machine can reach it (firewall, VPN), and "
            f"give --address HOST:6379, or ray://HOST:10001 with the Ray client extra "
            "(pip install 'ray[client]'); --connect-timeout SECONDS waits longer")


def probe(address: Address, timeout_s: float) -> None:
    """Open (and close) a TCP connection to the address, retrying until timeout_s; raise
    ClusterUnreachable naming the address, the reason and the fix. "auto" is not probed."""
    if address.host is None or address.port is None:
        return
    deadline = time.monotonic() + timeout_s
    reason = "no answer"
    while True:
        left = deadline - time.monotonic()
        try:
            with socket.create_connection((address.host, address.port),
                                          timeout=max(0.1, min(PROBE_ATTEMPT_S, left))):
                return
        except socket.gaierror as err:  # a name that does not resolve will not start to
            raise ClusterUnreachable(
                f"--address {address.text}: cannot resolve the host {address.host!r} "
                f"({err.strerror}); {_fix(address)}.") from err
        except OSError as err:
            reason = err.strerror or type(err).__name__
        if time.monotonic() + PROBE_PAUSE_S >= deadline:
            break
        time.sleep(PROBE_PAUSE_S)
    raise ClusterUnreachable(
        f"--address {address.text}: no Ray cluster answered at {address.host}:{address.port} "
        f"within {timeout_s:g} s ({reason}); {_fix(address)}.")


def connect(ray: Any, address_text: str, timeout_s: float, **init: Any) -> None:
    """ray.init(address=...) within timeout_s, or ClusterUnreachable naming the address, what
    happened and the fix (the token authentication hint when the port answered but Ray did
    not)."""
    address = parse_address(address_text)
    start = time.monotonic()
    probe(address, timeout_s)
    box: dict[str, BaseException] = {}
    done = threading.Event()

    def attempt() -> None:
        try:
            ray.init(address=address.text, **init)
        except BaseException as err:  # handed to the main thread, which raises it
            box["error"] = err
        finally:
            done.set()

    # A daemon thread: when Ray never answers, this process may still exit.
    threading.Thread(target=attempt, name="ray-connect", daemon=True).start()
    if not done.wait(max(0.1, timeout_s - (time.monotonic() - start))):
        auth = "" if os.environ.get("RAY_AUTH_MODE", "").lower() == "token" else f"; {AUTH_HINT}"
        raise ClusterUnreachable(
            f"--address {address.text}: the port answers but Ray did not accept this driver "
            f"within {timeout_s:g} s (a Ray of another version, another service on that port, "
            f"or a token it refused){auth}; otherwise {_fix(address)}.")
    error = box.get("error")
    if error is not None:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ClusterUnreachable(f"--address {address.text}: Ray could not connect: {first}; "
                                 f"{_fix(address)}.") from error


def classify(error: BaseException) -> Fault:
    """"lost" for an error that says the task's worker or node went away (run it again),
    "failed" for anything else. By class name, so that this module needs no Ray to test."""
    names = {cls.__name__ for cls in type(error).__mro__}
    return "lost" if names & LOST_ERRORS else "failed"
