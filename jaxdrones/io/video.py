"""Write RGB frames (e.g. from ``step.render``) to an MP4 or GIF file.

    with VideoWriter("flight.mp4", fps=24) as video:
        for state in states:
            video.append(step.render(params, state))

MP4 files are H.264 (yuv420p, readable by common players) written through imageio's ffmpeg plugin
(``imageio-ffmpeg`` ships an ffmpeg binary); GIFs are written by Pillow. A video is written beside its path and
moved there when closed; an existing file is replaced only with ``overwrite=True``, and only a video jaxdrones wrote
(`SIGNATURE`).
"""

from __future__ import annotations

import os
import warnings

import numpy as np
from numpy.typing import ArrayLike

from jaxdrones._validate import check_real
from jaxdrones.io.runs import check_replace

#: The mark of every video `VideoWriter` writes (MP4: its comment; GIF: its comment extension): ``overwrite``
#: replaces only a video that holds it (`jaxdrones.io.runs.check_replace`).
SIGNATURE = b"written by jaxdrones"

#: File extensions and their formats.
FORMATS = {".mp4": "mp4", ".gif": "gif"}


def video_format(path: str | os.PathLike) -> str:
    """The format of a video file, ``"mp4"`` or ``"gif"``, from its extension (`FORMATS`).

    Raises:
        ValueError: on another extension.
    """
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in FORMATS:
        raise ValueError(
            f"video path {path!r} has an unknown extension {ext!r}: expected a file name ending in one "
            f"of {tuple(FORMATS)}"
        )
    return FORMATS[ext]


class VideoWriter:
    """A context manager that appends uint8 RGB frames to a video file.

    Args:
        path: output file; its extension picks the format: ``.mp4`` (H.264 through imageio-ffmpeg) or ``.gif``
            (Pillow, looping forever). Missing parent folders are created.
        fps: frames per second, > 0. A GIF stores frame durations in 10 ms units, so its rate is rounded to that.
        overwrite: replace an existing video that jaxdrones wrote (`SIGNATURE`).

    Every frame must be uint8[H, W, 3] (RGB) with the first frame's shape. H.264 needs even sizes, so MP4 frames
    with an odd height or width are padded by repeating their last row or column. Frames are encoded as they come
    (MP4) or kept in memory until `close` (GIF, meant for short clips). Nothing is written when no frame was
    appended.

    Raises:
        ValueError: on an unknown extension or a bad fps (here), a frame that is not uint8[H, W, 3] or whose shape
            differs from the first frame's (in `append`), ``overwrite`` of a file jaxdrones did not write.
        FileExistsError: if ``path`` exists and not ``overwrite``.
    """

    def __init__(self, path: str | os.PathLike, fps: float = 24, overwrite: bool = False):
        path = os.fspath(path)
        video_format(path)
        check_real("fps", fps, 0, low_open=True, what="a finite number of frames per second")
        if os.path.isdir(path):
            raise ValueError(f"video path {path!r} is a folder")
        check_replace(path, overwrite, SIGNATURE, read=2**20)
        self.path = path
        root, ext = os.path.splitext(path)
        self._partial = f"{root}.partial-{os.getpid()}{ext}"  # written here, moved to ``path`` when closed
        self.fps = float(fps)
        self.format = video_format(path)
        self._overwrite = bool(overwrite)
        self._shape: tuple[int, ...] | None = None
        self._frames: list = []  # GIF: the frames as Pillow images
        self._writer = None  # MP4: the imageio writer, opened on the first frame
        self._count = 0
        self._closed = False

    @property
    def n_frames(self) -> int:
        """Number of frames appended so far."""
        return self._count

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def append(self, frame: ArrayLike) -> None:
        """Add one frame, uint8[H, W, 3] RGB (NumPy or JAX array), row 0 at the top.

        Raises:
            ValueError: if the frame is not uint8[H, W, 3], or its shape differs from the first frame's.
            RuntimeError: if the writer was closed.
        """
        if self._closed:
            raise RuntimeError(f"the video {self.path!r} was closed")
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3 or 0 in frame.shape:
            raise ValueError(f"a video frame must be uint8[H, W, 3] RGB, got {frame.dtype}{list(frame.shape)}")
        if self._shape is None:
            self._shape = frame.shape
            self._open()
        elif frame.shape != self._shape:
            raise ValueError(f"frame {self._count} has shape {frame.shape}, but the video's frames are {self._shape}")
        if self.format == "mp4":
            with warnings.catch_warnings():
                # The first frame starts ffmpeg as a subprocess; Python warns that forking a process with JAX's
                # threads could deadlock the child, which does not apply to a child that at once runs ffmpeg.
                warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
                self._writer.append_data(_pad_even(frame))
        else:
            from PIL import Image

            self._frames.append(Image.fromarray(frame, "RGB"))
        self._count += 1

    def close(self) -> None:
        """Finish the file (idempotent). Called by the ``with`` block."""
        if self._closed:
            return
        self._closed = True
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._frames:
            duration = max(10, int(round(100.0 / self.fps)) * 10)  # ms, in GIF's 10 ms units
            self._frames[0].save(
                self._partial, format="GIF", save_all=True, append_images=self._frames[1:], duration=duration,
                loop=0, comment=SIGNATURE,
            )  # fmt: skip
            self._frames = []
        if os.path.exists(self._partial):
            os.replace(self._partial, self.path)

    def _open(self) -> None:
        check_replace(self.path, self._overwrite, SIGNATURE, read=2**20)  # created since __init__?
        folder = os.path.dirname(self.path)
        if folder:
            os.makedirs(folder, exist_ok=True)
        if self.format == "mp4":
            import imageio.v2 as imageio

            self._writer = imageio.get_writer(
                self._partial,
                format="FFMPEG",
                mode="I",
                fps=self.fps,
                codec="libx264",
                pixelformat="yuv420p",
                macro_block_size=1,
                ffmpeg_log_level="error",
                # The mark of a video jaxdrones wrote, in the index that faststart puts at the file's start.
                output_params=["-metadata", f"comment={SIGNATURE.decode()}", "-movflags", "+faststart"],
            )


def _pad_even(frame: np.ndarray) -> np.ndarray:
    """Pad uint8[H, W, 3] to even H and W by repeating the last row / column (H.264 with yuv420p needs even sizes)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
