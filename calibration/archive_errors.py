"""Errors of sweep archives (:mod:`calibration.archive`): every one names what is wrong and
where, so the station and ``lfcal`` can say it plainly."""

from __future__ import annotations

import errno
import os
from pathlib import Path

# --------------------------------------------------------------------------- errors


class ArchiveError(ValueError):
    """An archive or one of its files is invalid; ``problems`` lists every problem found."""

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        self.problems: list[str] = list(problems) if problems is not None else [message]
        super().__init__(message)


class ImageError(ArchiveError):
    """An image file cannot be used; ``path`` is the offending file."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class MissingImageError(ImageError, FileNotFoundError):
    """The image file does not exist."""


class CorruptImageError(ImageError):
    """The file is not a decodable PNG (bad signature, truncated, damaged data)."""


class WrongImageSizeError(ImageError):
    """The image does not have the manifest's ``height × width``."""


class BitDepthError(ImageError):
    """Pixel values exceed ``2**bit_depth − 1`` or the PNG has too few bits per sample."""


class NotGrayscaleError(ImageError):
    """The PNG has colour channels or an alpha channel."""


class ArchiveExistsError(FileExistsError):
    """The destination already holds an archive (and overwriting was not asked for)."""


class DuplicateFrameError(ValueError):
    """A frame with this index is already recorded in the manifest."""


class DiskFull(OSError):  # noqa: N818 - the station catches it by this name
    """Not enough free disk space for a write.

    ``path`` is the file that was to be written, ``needed_bytes`` its size plus the
    reserve, ``free_bytes`` what the file system had available.
    """

    def __init__(self, path: str | os.PathLike[str], needed_bytes: int, free_bytes: int) -> None:
        self.path = Path(path)
        self.needed_bytes = int(needed_bytes)
        self.free_bytes = int(free_bytes)
        super().__init__(
            errno.ENOSPC,
            f"not enough disk space to write {path}: need {needed_bytes} bytes, "
            f"{free_bytes} bytes free",
        )

    def __str__(self) -> str:
        return str(self.strerror)
