"""OpenIGTLink out, as PLUS speaks it: every tool's TRANSFORM on every frame, with its status.

3D Slicer (OpenIGTLinkIF) and PLUS clients read the poses as TRANSFORM messages named
``<Tool>ToTracker`` (or ``<Tool>ToReference``, relative to a reference tool). What they
expect of a tracker, and what :class:`IGTLSender` and :class:`IGTLToolsSender` send:

- **A timestamp in seconds since the Unix epoch**: the frame's capture time (live
  cameras), or the run's start plus the frame's time in the recording.
- **A status on every frame**: a header-version-2 message whose metadata carry PLUS's
  ``TransformStatus`` (``OK``, ``MISSING``, ``OUT_OF_VOLUME``, ``INVALID``) and
  ``TransformValid`` (``1`` / ``0``), plus markerpose's own ``MarkerposeStatus``
  (:meth:`markerpose.results.Estimate.status`) and ``SdMm`` (the pose's 1-sigma RMS error).
  A tool not found sends the identity with ``MISSING``: never the last pose as if new.
- **Any number of clients**: :class:`IGTLServer` accepts them all and sends each message to
  each; a client that leaves, stalls or sends garbage is dropped with a one-line notice and
  costs the others nothing. What clients send is read and ignored (commands are not served).

``pyigtl`` (the igtl extra) packs the messages; the server is this module's own, as
pyigtl's serves one client.
"""

from __future__ import annotations

import selectors
import socket
import sys
import threading

import numpy as np

DEFAULT_PORT = 18944
CAMERA = "camera"  # the frame of a pose in the left camera's (video.CAMERA)
# Our pose status (Estimate.status) -> PLUS's tool status (igsio ToolStatus strings).
PLUS_STATUS = {
    "ok": "OK",
    "low accuracy": "OK",
    "unrated": "OK",
    "outside the calibrated volume": "OUT_OF_VOLUME",
    "rig changed": "INVALID",
}
MISSING = "MISSING"
SEND_TIMEOUT_S = 0.5  # a client that has not taken a message within this is dropped
NAME_BYTES = 20  # the header's device-name field


def igtl_device_name(tool: str, relative_to: str = CAMERA) -> str:
    """The OpenIGTLink device name of a tool's pose, PLUS's way: ``Tool1ToTracker`` for
    ``tool1`` in the camera's frame, ``Tool1ToReference`` relative to the reference tool."""
    return f"{tool[:1].upper()}{tool[1:]}To{'Tracker' if relative_to == CAMERA else 'Reference'}"


def _pyigtl():
    try:
        import pyigtl
    except ImportError as exc:
        raise ValueError('--igtl needs pyigtl: pip install -e ".[igtl]"') from exc
    return pyigtl


def transform_message(name: str, T, timestamp: float, status: str | None, sd_mm: float | None = None) -> bytes:
    """One TRANSFORM message, packed: ``T`` (4 x 4, mm) named ``name`` at ``timestamp``
    (seconds since the epoch) with our ``status`` (:meth:`~markerpose.results.Estimate.status`),
    or, with ``T`` None, the identity with status ``MISSING`` (see the module's docstring)."""
    pyigtl = _pyigtl()
    valid_pose = T is not None
    msg = pyigtl.TransformMessage(np.eye(4) if T is None else np.asarray(T, np.float64), timestamp=float(timestamp))
    msg.device_name = name[:NAME_BYTES]
    plus = PLUS_STATUS.get(status or "ok", "INVALID") if valid_pose else MISSING
    msg.header_version = 2
    msg.metadata = {
        "TransformStatus": plus,
        "TransformValid": "1" if plus == "OK" else "0",
        "MarkerposeStatus": (status or "ok") if valid_pose else "not found",
    }
    if sd_mm is not None and np.isfinite(sd_mm):
        msg.metadata["SdMm"] = f"{sd_mm:.6f}"
    if len(name) > NAME_BYTES:  # PLUS's way with a name the header cannot hold
        msg.metadata["IGTL_DEVICE_NAME"] = name
    return msg.pack()


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class IGTLServer:
    """A TCP server for OpenIGTLink clients: any number at once, each sent every message
    (:meth:`broadcast`); see the module's docstring.

    Args:
        port: TCP port (OpenIGTLink's default is 18944).
        local_only: listen on 127.0.0.1 only (False: every interface).
        notice: called with a one-line message when a client comes or goes.
    """

    def __init__(self, port: int = DEFAULT_PORT, local_only: bool = True, notice=_say):
        self.port, self.notice = int(port), notice
        try:
            self._listener = socket.create_server(("127.0.0.1" if local_only else "", self.port))
        except OSError as exc:
            raise ValueError(f"cannot serve OpenIGTLink on port {port}: {exc.strerror or exc}") from exc
        self._listener.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self._clients: dict[socket.socket, str] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.served = 0  # clients accepted so far
        self._thread = threading.Thread(target=self._serve, name="openigtlink", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        """The number of clients connected now."""
        with self._lock:
            return len(self._clients)

    def is_connected(self) -> bool:
        return self.clients > 0

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                events = self._selector.select(timeout=0.1)
            except (OSError, ValueError):  # a socket closed under the selector: look again
                continue
            for key, _ in events:
                sock = key.fileobj
                if sock is self._listener:
                    self._accept()
                    continue
                with self._lock:
                    known = sock in self._clients
                if not known:
                    continue
                try:
                    data = sock.recv(65536)  # commands are not served: read and dropped
                except OSError as exc:
                    self._drop(sock, exc.strerror or type(exc).__name__)
                    continue
                if not data:
                    self._drop(sock, "disconnected")

    def _accept(self) -> None:
        try:
            sock, addr = self._listener.accept()
        except OSError:
            return
        sock.setblocking(True)
        sock.settimeout(SEND_TIMEOUT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # a pose a frame: no batching delay
        name = f"{addr[0]}:{addr[1]}"
        with self._lock:
            self._clients[sock] = name
            self._selector.register(sock, selectors.EVENT_READ)
            n = len(self._clients)
        self.served += 1
        self.notice(f"OpenIGTLink: client {name} connected ({n} connected)")

    def _drop(self, sock: socket.socket, why: str) -> None:
        with self._lock:
            name = self._clients.pop(sock, None)
            if name is None:
                return
            try:
                self._selector.unregister(sock)
            except (KeyError, ValueError, OSError):
                pass
            n = len(self._clients)
        try:
            sock.close()
        except OSError:
            pass
        self.notice(f"OpenIGTLink: client {name} left ({why}; {n} connected)")

    def broadcast(self, data: bytes) -> int:
        """Send ``data`` to every client; the number that took it (a client that fails is dropped)."""
        with self._lock:
            clients = list(self._clients)
        sent = 0
        for sock in clients:
            try:
                sock.sendall(data)
                sent += 1
            except TimeoutError:
                self._drop(sock, f"took no message for {SEND_TIMEOUT_S:g} s")
            except OSError as exc:
                self._drop(sock, exc.strerror or type(exc).__name__)
        return sent

    def stop(self) -> None:
        """Close every client and the port."""
        self._stop.set()
        self._thread.join(timeout=2)
        with self._lock:
            clients = list(self._clients)
            self._clients.clear()
        for sock in clients:
            try:
                sock.close()
            except OSError:
                pass
        self._selector.close()
        self._listener.close()


class IGTLSender:
    """Sends one marker's pose each frame as a TRANSFORM named ``name`` (millimetres,
    T_left_marker), with its status, to every client of an :class:`IGTLServer` (see the
    module's docstring). Nothing is queued while no client is connected: a client that
    connects later gets the next frame, never a stale pose.

    Args:
        port: TCP port (OpenIGTLink's default is 18944).
        name: the device name (e.g. "MarkerToTracker").
        local_only: listen on 127.0.0.1 only (False: every interface).
        notice: called with a one-line message when a client comes or goes.
    """

    def __init__(self, port: int = DEFAULT_PORT, name: str = "MarkerToTracker", local_only: bool = True, notice=_say):
        _pyigtl()
        self.name = name
        self.server = IGTLServer(port, local_only, notice)
        self.sent = 0  # messages sent (to at least one client)

    def __call__(self, k: int, timestamp: float, est) -> bool:
        """Send frame ``k``'s pose (or its absence) stamped ``timestamp`` (seconds since the
        epoch); whether a client took it."""
        if not self.server.is_connected():
            return False
        if est is None:
            return self._send(self.name, None, timestamp)
        return self._send(self.name, est.T, timestamp, est.status(), est.sd_mm)

    def _send(self, name: str, T, timestamp: float, status: str | None = None, sd: float | None = None) -> bool:
        if self.server.broadcast(transform_message(name, T, timestamp, status, sd)):
            self.sent += 1
            return True
        return False

    def close(self) -> None:
        self.server.stop()


class IGTLToolsSender(IGTLSender):
    """An :class:`IGTLSender` for several tools: each frame, one TRANSFORM per tool
    (:class:`~markerpose.video.ToolReport`), named by :func:`igtl_device_name`
    (``Tool1ToTracker``, or ``Tool1ToReference`` relative to the reference tool); a tool
    not reported (not found, or its reference not seen) is sent as ``MISSING``.

    Args:
        port: TCP port (OpenIGTLink's default is 18944).
        tools: the tools' names, to check that their device names differ.
        reference: the reference tool's name, or None.
        local_only: listen on 127.0.0.1 only (False: every interface).
        notice: called with a one-line message when a client comes or goes.
    """

    def __init__(self, port: int = DEFAULT_PORT, tools=(), reference: str | None = None, local_only: bool = True, notice=_say):
        self.devices = {n: igtl_device_name(n, CAMERA if reference in (None, n) else reference) for n in tools}
        seen: dict[str, str] = {}
        for tool, device in self.devices.items():
            if device in seen:
                raise ValueError(f"the tools {seen[device]!r} and {tool!r} would both be sent as {device!r} over OpenIGTLink; rename one")
            seen[device] = tool
        super().__init__(port, name=None, local_only=local_only, notice=notice)

    def __call__(self, k: int, timestamp: float, reports) -> int:
        """Send frame ``k``'s reports (stamped ``timestamp``, seconds since the epoch); the
        number of valid poses sent."""
        if not self.server.is_connected():
            return 0
        from .uncertainty import sd_mm

        valid = 0
        for r in reports:
            name = igtl_device_name(r.name, r.relative_to)
            if r.valid:
                self._send(name, r.T, timestamp, r.est.status() if hasattr(r.est, "status") else None, sd_mm(r.cov, r.T))
            else:
                self._send(name, None, timestamp)
            valid += r.valid
        return valid


__all__ = ["DEFAULT_PORT", "IGTLSender", "IGTLServer", "IGTLToolsSender", "MISSING", "PLUS_STATUS", "igtl_device_name", "transform_message"]
