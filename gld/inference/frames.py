"""A recording's frames, read one at a time and cached for the pairs that share them: an
image folder (`ImageFolderFrames`) or a video (`VideoFrames`), each frame named (the
file's stem, or the video frame's number with `VIDEO_NAME_DIGITS` digits)."""

from __future__ import annotations

import collections
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

VIDEO_NAME_DIGITS = 6


def read_frame_file(path: str | Path) -> np.ndarray:
    """An image file as stored: [H, W] greyscale, [H, W, 3] RGB or [H, W, 4] RGBA, in its
    own dtype (the predictor's rules decide what is accepted)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    if image.ndim == 3 and image.shape[-1] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[-1] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


class CachedFrames:
    """Random access to frames with the most recently used ones kept."""

    def __init__(self, names: Sequence[str], cache_size: int):
        self.names = list(names)
        self._cache: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self.cache_size = max(2, cache_size)

    def __len__(self) -> int:
        return len(self.names)

    def _keep(self, index: int, frame: np.ndarray) -> None:
        self._cache[index] = frame
        self._cache.move_to_end(index)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def _read(self, index: int) -> np.ndarray:
        raise NotImplementedError

    def read(self, index: int) -> np.ndarray:
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        frame = self._read(index)
        self._keep(index, frame)
        return frame

    def close(self) -> None:
        self._cache.clear()


class ImageFolderFrames(CachedFrames):
    """Frames from image files (in the given order), named by their file names' stems."""

    def __init__(self, paths: Sequence[str | Path], cache_size: int = 8):
        self.paths = [Path(path) for path in paths]
        if not self.paths:
            raise ValueError("no image files given")
        super().__init__([path.stem for path in self.paths], cache_size)

    def _read(self, index: int) -> np.ndarray:
        return read_frame_file(self.paths[index])


class VideoFrames(CachedFrames):
    """Frames of a video file (OpenCV), named by their index (000000, 000001, ...).

    Frames are decoded in order; those decoded on the way to a later frame stay in the
    cache, so pairs taken in recording order decode each frame once. An earlier frame
    that has left the cache is reached by seeking.
    """

    def __init__(self, path: str | Path, cache_size: int = 8):
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"video {self.path} does not exist")
        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise ValueError(f"cannot open video {self.path} with OpenCV")
        count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            raise ValueError(f"video {self.path}: OpenCV reports no frames")
        self._position = 0
        super().__init__([f"{i:0{VIDEO_NAME_DIGITS}d}" for i in range(count)], cache_size)

    def _read(self, index: int) -> np.ndarray:
        if index < self._position or index - self._position > self.cache_size:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, index)
            self._position = index
        while True:
            ok, frame = self._capture.read()
            if not ok:
                raise ValueError(
                    f"video {self.path}: cannot decode frame {self._position} (the file "
                    f"reports {len(self.names)} frames)"
                )
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
            self._position += 1
            if self._position - 1 == index:
                return frame
            self._keep(self._position - 1, frame)

    def close(self) -> None:
        super().close()
        self._capture.release()
