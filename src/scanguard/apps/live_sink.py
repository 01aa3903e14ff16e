"""The live view: a run's messages (`scanguard.apps.viz_sink`) on a Foxglove WebSocket server.

Served by the official ``foxglove-sdk`` (import name ``foxglove``, the ``scanguard[viz]``
extra), in a context of its own so that nothing else logged in the process reaches the
clients. The SDK queues a bounded number of messages per client (`BACKLOG`) and drops the
oldest when a client falls behind, so a slow or absent client never slows the run. The server
binds 127.0.0.1 unless told otherwise, and is stopped when the block is left (Ctrl-C
included), waiting at most `STOP_TIMEOUT` for it: the SDK's ``stop`` waits for every client's
queue to drain, which a client that connected and never reads never lets happen (and no
signal reaches Python while it waits).
"""

from __future__ import annotations

import logging
import threading
from types import TracebackType
from typing import Any

from scanguard.apps.viz_messages import ChannelSpec
from scanguard.errors import ConfigError

logger = logging.getLogger(__name__)

#: The one-line message of ``--live`` without the extra.
VIZ_MISSING = "--live needs the viz extra: pip install 'scanguard[viz]' (foxglove-sdk)"
#: Default port of the Foxglove WebSocket protocol.
LIVE_PORT = 8765
#: Messages queued per client before the oldest are dropped (a map frame can be megabytes:
#: a client that stopped reading holds at most this many).
BACKLOG = 64
#: Seconds the end of a run waits for the server to stop; then it is left to the process exit.
STOP_TIMEOUT = 2.0


def import_foxglove() -> Any:
    """The ``foxglove`` module.

    Raises:
        ConfigError: ``foxglove-sdk`` is not installed (`VIZ_MISSING`).
    """
    try:
        import foxglove
    except ImportError:
        raise ConfigError(VIZ_MISSING) from None
    return foxglove


class LiveOutput:
    """An `scanguard.apps.viz_sink.Output` serving a Foxglove WebSocket; a context manager.

    Args:
        host: Address to bind (127.0.0.1: this machine only).
        port: Port (0: any free port, see `port`).

    Raises:
        ConfigError: ``foxglove-sdk`` is not installed, or the server cannot listen there.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = LIVE_PORT) -> None:
        self.foxglove = import_foxglove()
        self.host, self.requested_port = host, port
        self.server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self.server.port)

    def __enter__(self) -> LiveOutput:
        fg = self.foxglove
        self._context = fg.Context()
        try:
            self.server = fg.start_server(
                name="scanguard",
                host=self.host,
                port=self.requested_port,
                context=self._context,
                message_backlog_size=BACKLOG,
            )
        except Exception as exc:  # the SDK raises its own error types
            raise ConfigError(
                f"cannot serve the live view on {self.host}:{self.requested_port}: {exc}"
            ) from None
        logger.info("live view: ws://%s:%d (Foxglove: open a connection)", self.host, self.port)
        return self

    def add_channel(self, spec: ChannelSpec) -> None:
        """Advertise the channel to the clients."""
        fg = self.foxglove
        schema = fg.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema)
        self._channels[spec.topic] = fg.Channel(
            spec.topic, schema=schema, message_encoding=spec.encoding, context=self._context
        )

    def write(self, topic: str, data: bytes, ns: int) -> None:
        """Send one message to the clients subscribed to ``topic`` (never blocks)."""
        self._channels[topic].log(data, log_time=ns)

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # in a thread: a client that never reads blocks the SDK's stop (and every signal)
        done = threading.Thread(target=self._shutdown, name="scanguard-live-stop", daemon=True)
        done.start()
        done.join(STOP_TIMEOUT)
        if done.is_alive():
            logger.warning(
                "live view: a client did not read its messages; stopped without waiting for it "
                "(after %g s)",
                STOP_TIMEOUT,
            )
        else:
            logger.info("live view closed")

    def _shutdown(self) -> None:
        for channel in self._channels.values():
            channel.close()
        if self.server is not None:
            self.server.stop()
