"""Ray for the work that outgrows one machine (the report's cells): one address setting, checked first,
and one-line failures instead of hangs.

An address is one of

* ``local``: start a Ray instance on this machine with ``num_cpus`` CPUs; it is shut down afterwards;
* ``auto``: join the cluster this machine belongs to (started with ``ray start`` / ``ray up``, or named
  by ``RAY_ADDRESS``);
* ``host:port``: join the cluster whose head (GCS) listens there (``ray start --head`` prints it);
* ``ray://host:port``: connect through Ray Client (port 10001 on the head by default).

A Ray already initialised in this process (a test's, a notebook's) is used as it is and left running: only
what :func:`ray_session` started is shut down. Before ``ray.init`` joins a cluster, its port is tried
with a plain TCP connection (``probe_timeout_s``), so an address nobody listens on fails in one line within
seconds; ``auto`` without a cluster, too (a port that answers but is no Ray head, or a network that accepts
every connection, gets Ray's own connection attempts first: about 20 s, with Ray's warnings on stderr, then
one line). Ray not installed: one line naming the extra. Ray's own
SIGTERM handler (``ray.init`` installs one that calls ``sys.exit``) is taken back out, so a run's
graceful termination (:func:`torcsrl.utils.faults.graceful_termination`) still stops it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

__all__ = ["ADDRESS_HELP", "RayError", "RayInfo", "check_address", "import_ray", "probe", "ray_session"]

#: What an address may be (for one-line errors).
ADDRESS_HELP = "null (no Ray), local (a Ray instance on this machine), auto (the running cluster), host:port or ray://host:port"
INSTALL_HINT = "pip install 'torcsrl[distributed]'"


class RayError(ValueError):
    """A bad Ray address, a cluster that cannot be reached, or Ray not installed (one line)."""


@dataclass
class RayInfo:
    """What :func:`ray_session` connected to: the address asked for, the one joined (``local``; ``host:port``;
    ``""`` for the Ray this process had initialised already), the cluster's CPUs, and whether this session
    called ``ray.init`` (and so calls ``ray.shutdown``)."""

    address: str
    joined: str
    cpus: int
    started: bool

    def describe(self) -> str:
        where = ("a local Ray instance" if self.joined == "local" else f"the Ray cluster at {self.joined}" if self.joined
                 else "the Ray instance this process had initialised")
        return f"{where}, {self.cpus} CPU(s)"


def _host_port(address: str) -> tuple[str, int]:
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    host = host.strip("[]")  # [::1]:6379
    if not sep or not host or "/" in host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RayError(f"ray: {address!r} is not a Ray address; allowed: {ADDRESS_HELP}")
    return host, int(port)


def check_address(address: Any) -> str | None:
    """The address, stripped, or None for no Ray; :class:`RayError` (one line) for anything else. No network."""
    if address is None:
        return None
    if not isinstance(address, str) or not address.strip():
        raise RayError(f"ray: {address!r} is not a Ray address; allowed: {ADDRESS_HELP}")
    a = address.strip()
    if a not in ("local", "auto"):
        _host_port(a)
    return a


def import_ray():
    """The ``ray`` module, or :class:`RayError` saying how to install it."""
    try:
        import ray  # deferred: optional (the [distributed] extra)
    except ImportError:
        raise RayError(f"running on Ray needs the ray package, which is not installed: {INSTALL_HINT}") from None
    return ray


def probe(address: str, timeout_s: float = 5.0) -> None:
    """Open (and close) a TCP connection to ``host:port`` of ``address``; :class:`RayError` naming the address
    when nothing answers within ``timeout_s``."""
    host, port = _host_port(address)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as err:
        reason = "timed out" if isinstance(err, socket.timeout) else (err.strerror or str(err))
        raise RayError(f"ray: cannot reach the Ray cluster at {address} ({reason} within {timeout_s:g} s); allowed: "
                       f"{ADDRESS_HELP}, of a cluster that is running (ray start --head prints its address)") from None


def _resolve_auto() -> str:
    """The address ``auto`` means (RAY_ADDRESS, else the cluster ``ray start`` recorded on this machine);
    RayError when there is none."""
    env = os.environ.get("RAY_ADDRESS", "").strip()
    if env:
        return env
    try:
        from ray._private.services import canonicalize_bootstrap_address_or_die  # deferred: optional (ray)
    except ImportError:  # pragma: no cover - Ray moved it: ray.init finds it itself
        return "auto"
    try:
        return canonicalize_bootstrap_address_or_die("auto")
    except ConnectionError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else "none found"
        raise RayError(f"ray: auto found no running Ray cluster on this machine ({first}); allowed: {ADDRESS_HELP}; "
                       "start one with `ray start --head`, or use ray=local") from None


@contextlib.contextmanager
def ray_session(address: str, num_cpus: int | None = None, probe_timeout_s: float = 5.0) -> Iterator[tuple[Any, RayInfo]]:
    """Connect to Ray at ``address`` (see the module docstring; ``num_cpus`` only for ``local``), yield
    ``(ray, RayInfo)``, and shut Ray down after if this call started or joined it (not when this process had
    initialised Ray already). Every failure to connect is a :class:`RayError` with one line."""
    address = check_address(address)
    if address is None:
        raise RayError(f"ray: no address; allowed: {ADDRESS_HELP}")
    ray = import_ray()
    if ray.is_initialized():
        cpus = int(ray.cluster_resources().get("CPU", 1))
        yield ray, RayInfo(address, "", cpus, started=False)
        return
    joined = address
    if address == "auto":
        joined = _resolve_auto()
    if joined != "local" and joined != "auto":
        probe(joined, probe_timeout_s)
    kwargs: dict[str, Any] = {"logging_level": logging.WARNING}
    if joined == "local":
        kwargs.update(num_cpus=num_cpus, include_dashboard=False)
    main = threading.current_thread() is threading.main_thread()
    old_term = signal.getsignal(signal.SIGTERM) if main else None
    try:
        ray.init(address=joined, **kwargs)
    except ConnectionError as err:  # auto without a cluster, a head that went away
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RayError(f"ray: cannot connect to Ray at {address} ({first}); allowed: {ADDRESS_HELP}") from None
    finally:
        if main and old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        yield ray, RayInfo(address, joined, cpus, started=True)
    finally:
        ray.shutdown()  # a local instance stops; a cluster only loses this driver
