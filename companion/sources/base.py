"""The one interface every camera source implements: ``read() -> Frame | None``.

A source is opened, read frame by frame and closed; it is also a context manager and an
iterator (iteration stops when :meth:`FrameSource.read` returns None, the end of a recording
or of a scripted flight). Live sources never return None on a bad frame: they skip it, count
it in :attr:`FrameSource.dropped_frames` and wait for the next.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from types import TracebackType

from semmap.types import CameraIntrinsics, Frame


class FrameSource(ABC):
    """An RGB-D camera: simulated, recorded or live."""

    #: Frames delivered so far.
    frames_read: int = 0
    #: Frames skipped because they were incomplete or malformed (live sources).
    dropped_frames: int = 0

    @property
    @abstractmethod
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the frames this source delivers (depth aligned to colour)."""

    def open(self) -> None:
        """Acquire the device or files. Idempotent; :meth:`read` opens on first use.
        Sources with nothing to acquire (the simulator) keep this default."""
        return None

    def close(self) -> None:
        """Release the device or files. Idempotent."""
        return None

    @abstractmethod
    def read(self) -> Frame | None:
        """The next frame, or None at the end of the stream. Raises
        :class:`~semmap.errors.FrameError` when a frame cannot be produced."""

    def __enter__(self) -> FrameSource:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame


class WrappedSource(FrameSource):
    """A stage wrapped around another source (``inner``): the camera's intrinsics, counters,
    open and close pass through; subclasses change what :meth:`read` returns."""

    def __init__(self, inner: FrameSource) -> None:
        self.inner = inner

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.inner.intrinsics

    @property
    def dropped_frames(self) -> int:  # type: ignore[override]
        return self.inner.dropped_frames

    @property
    def frames_read(self) -> int:  # type: ignore[override]
        return self.inner.frames_read

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def read(self) -> Frame | None:
        return self.inner.read()
