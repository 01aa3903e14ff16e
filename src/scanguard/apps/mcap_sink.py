"""``result.mcap``: the view of a run (`scanguard.apps.viz_sink`) written as one MCAP file.

Written with the ``mcap`` package's writer (zstd chunks, an index and statistics, so ``mcap
info`` and Foxglove seek in it), under the ``ros2`` profile: ROS 2 channels carry ``cdr``
messages with ``ros2msg`` schemas, as ``rosbag2`` writes them; the guard's decisions are JSON.
The file is written to a temporary sibling and renamed into place when it is complete
(`scanguard.fsutil.atomic_path`): a failed or interrupted run leaves no partial file.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

from scanguard.apps.viz_messages import ChannelSpec
from scanguard.errors import OutputError
from scanguard.fsutil import atomic_path

#: File name of the view in a run's output folder.
MCAP_NAME = "result.mcap"


class McapOutput:
    """An `scanguard.apps.viz_sink.Output` writing one MCAP file; a context manager.

    Args:
        path: The MCAP file (written atomically when the block is left without an error).

    Raises:
        OutputError: The file cannot be written.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._atomic: AbstractContextManager[Path] | None = None
        self._file: BinaryIO | None = None
        self._writer: Any = None
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}

    def __enter__(self) -> McapOutput:
        from mcap.writer import Writer

        self._atomic = atomic_path(self.path)
        tmp = self._atomic.__enter__()
        try:
            self._file = open(tmp, "wb")  # closed in __exit__
        except OSError as exc:
            self._atomic.__exit__(type(exc), exc, None)
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library="scanguard")
        return self

    def add_channel(self, spec: ChannelSpec) -> None:
        """Register the channel (and its schema, once per schema)."""
        key = (spec.schema_name, spec.schema_encoding, spec.schema)
        if key not in self._schemas:
            self._schemas[key] = self._writer.register_schema(
                name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema
            )
        self._channels[spec.topic] = self._writer.register_channel(
            topic=spec.topic, message_encoding=spec.encoding, schema_id=self._schemas[key]
        )

    def write(self, topic: str, data: bytes, ns: int) -> None:
        """One message; log time = publish time = ``ns``."""
        try:
            self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns)
        except OSError as exc:
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self._atomic is not None and self._file is not None
        error = exc
        try:
            if exc_type is None:
                self._writer.finish()
        except BaseException as failed:  # the half-written file must not be moved into place
            error = failed
            raise
        finally:
            self._file.close()
            self._atomic.__exit__(None if error is None else type(error), error, tb)
