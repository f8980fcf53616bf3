"""headalign: self-calibration and self-alignment of active stereo heads.

The library, called in process (no subprocess, no temporary files), with numpy arrays in
and out:

- :func:`calibrate` self-calibrates a stereo rig from views related by rigid motions of
  the whole rig (a folder, a recording, or a list of ``(left, right)`` ``uint8`` arrays)
  and returns a :class:`Calibration` in OpenCV's conventions.
- :func:`align` runs the verge/tilt alignment of a recorded head run and returns an
  :class:`Alignment` (aligned readings, their sigmas, the head's calibration).
- :func:`check` checks a given calibration against stereo pairs of natural scenes (the
  right camera's rotation change, the depth error it causes, a verdict), and
  :func:`read_calibration` reads a calibration file (headalign JSON, OpenCV stereo YAML,
  Kalibr camchain).
- :func:`read_image` reads a PNG or JPEG file as a grey ``uint8`` array.

Bad input raises ``ValueError``, a failed estimation ``RuntimeError``. Long calls release
the GIL. The API, an example and the conventions shared with OpenCV: docs/python.md.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Callable, Optional, Sequence, Tuple, Union

import numpy as np

from . import _headalign
from ._headalign import Alignment, Calibration, CheckReport, __version__, read_calibration, read_image

__all__ = [
    "Alignment",
    "Calibration",
    "CheckReport",
    "align",
    "calibrate",
    "check",
    "read_calibration",
    "read_image",
    "__version__",
]

PathLike = Union[str, "os.PathLike[str]"]


class _Progress:
    """The library's progress reports as a bar: tqdm when installed, else one line on stderr.

    Called as ``progress(stage, message, done, total)`` (stages ``tracking``, ``tracked``,
    ``solving``, ``solved``), from the estimation's thread with the GIL held.
    """

    def __init__(self) -> None:
        try:
            from tqdm.auto import tqdm  # type: ignore[import-not-found]
        except ImportError:
            tqdm = None
        self._tqdm = tqdm
        self._bar: Any = None
        self._message = ""

    def __call__(self, stage: str, message: str, done: int, total: int) -> None:
        if stage == "tracking" and total > 0:
            if self._bar is None or message != self._message:
                self._close()
                self._open(message, total)
            self._update(done, total)
        elif stage == "solving":
            self._close()
            self._line(message + " ...", end=True)
        else:
            self._close()

    def _open(self, message: str, total: int) -> None:
        self._message = message
        if self._tqdm is not None:
            self._bar = self._tqdm(total=total, desc=message, unit="view", leave=False)
        else:
            self._bar = [0, total]

    def _update(self, done: int, total: int) -> None:
        if self._tqdm is not None:
            self._bar.update(max(done - self._bar.n, 0))
            return
        self._bar[0] = done
        width = 30
        filled = width * done // max(total, 1)
        self._line(f"\r{self._message} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")

    def _close(self) -> None:
        if self._bar is None:
            return
        if self._tqdm is not None:
            self._bar.close()
        else:
            self._line("", end=True)
        self._bar = None

    @staticmethod
    def _line(text: str, end: bool = False) -> None:
        sys.stderr.write(text + ("\n" if end else ""))
        sys.stderr.flush()


def _progress_callback(progress: Union[bool, Callable[..., Any], None]) -> Optional[Callable[..., Any]]:
    if progress is True:
        return _Progress()
    if callable(progress):
        return progress
    return None


def _as_views(views: Any) -> Any:
    """A path as it is; otherwise the pairs with each image as a numpy array (not copied)."""
    if isinstance(views, (str, bytes, os.PathLike)):
        return os.fsdecode(views)
    try:
        pairs = list(views)
    except TypeError:
        raise ValueError(
            f"views must be a path or a list of (left, right) image pairs, got {type(views).__name__}"
        ) from None
    out = []
    for i, pair in enumerate(pairs):
        try:
            left, right = pair
        except (TypeError, ValueError):
            raise ValueError(f"view {i}: expected a (left, right) pair of images") from None
        out.append((np.asarray(left), np.asarray(right)))
    return out


def calibrate(
    views: Union[PathLike, Sequence[Tuple[np.ndarray, np.ndarray]]],
    *,
    lens: str = "auto",
    lens_terms: Optional[str] = None,
    square_pixels: bool = False,
    fix_principal_point: bool = False,
    free_skew: bool = False,
    corners: Optional[int] = None,
    seed: int = 0,
    baseline_m: Optional[float] = None,
    every: int = 1,
    progress: Union[bool, Callable[[str, str, int, int], Any]] = False,
) -> Calibration:
    """Self-calibrate a stereo rig from views related by rigid motions of the whole rig.

    The same estimation as ``headalign calibrate``, with the same defaults: the same
    views and options give the same numbers.

    Args:
        views: a path (a folder of stereo pairs ``left*.png`` / ``right*.png``, an image
            or point session, a ROS 2 bag or an EuRoC folder), or a list of
            ``(left, right)`` numpy ``uint8`` arrays of shape ``(height, width)``, all of
            one size, in the order they were taken (at least two views with the rig
            moved between them).
        lens: the lens model estimated: ``"auto"`` (chosen by BIC and reported),
            ``"pinhole"``, ``"radtan"`` (OpenCV's plumb_bob), ``"equidistant"`` (OpenCV's
            fisheye) or ``"ds"`` (double sphere).
        lens_terms: the coefficients estimated: ``"radial"`` (k1 k2), ``"4"`` or ``"5"``;
            default ``radial``, and every term for ``auto``.
        square_pixels: ``fx = fy`` in both cameras.
        fix_principal_point: hold both principal points at the image centre.
        free_skew: estimate the skews (default: held at zero).
        corners: corners detected per image, no retry (default 1500, then 3000 when
            that result is weak or fails).
        seed: seed of the robust estimators.
        baseline_m: the baseline length in metres, to get ``T`` in metres (otherwise
            ``T`` is a unit vector, in baselines).
        every: read every N-th pair of a folder or recording.
        progress: ``True`` shows a progress bar on stderr (tqdm when installed); a
            callable gets ``(stage, message, done, total)``.

    Returns:
        The :class:`Calibration`.

    Raises:
        ValueError: bad input (dtype, shape, sizes, an option, a path with no views).
        RuntimeError: the estimation failed (too few tracks, a motion that cannot
            calibrate, ...).
    """
    return _headalign.calibrate(
        _as_views(views),
        lens,
        lens_terms,
        free_skew,
        square_pixels,
        fix_principal_point,
        corners,
        seed,
        baseline_m,
        every,
        _progress_callback(progress),
    )


def align(
    session: PathLike,
    *,
    lens: Optional[str] = None,
    lens_terms: Optional[str] = None,
    baseline_m: Optional[float] = None,
    progress: Union[bool, Callable[[str, str, int, int], Any]] = False,
) -> Alignment:
    """The verge/tilt alignment of a recorded head run, as ``headalign align`` runs it.

    Args:
        session: an observation file (``headalign-observations/1`` JSON), or a recorded
            session folder (image or point session), a ROS 2 bag or an EuRoC folder of a
            head run; images are tracked by the default front end.
        lens: the lens model estimated (default: the one a recorded session names, else
            ``"auto"`` for images and ``"pinhole"`` for tracked points).
        lens_terms: the coefficients estimated, as in :func:`calibrate`.
        baseline_m: the baseline length in metres, for the calibration's ``T``.
        progress: as in :func:`calibrate`.

    Returns:
        The :class:`Alignment`.

    Raises:
        ValueError: bad input (a path that holds no session, an option).
        RuntimeError: the estimation failed.
    """
    return _headalign.align(os.fsdecode(session), lens, lens_terms, baseline_m, _progress_callback(progress))


def check(
    views: Union[PathLike, Sequence[Tuple[np.ndarray, np.ndarray]]],
    calibration: Union[Calibration, PathLike],
    *,
    baseline_m: Optional[float] = None,
    corners: Optional[int] = None,
    seed: int = 0,
    significance: float = 5.0,
    depth_limit_pct: float = 1.0,
    progress: Union[bool, Callable[[str, str, int, int], Any]] = False,
) -> CheckReport:
    """Is a stereo calibration still good? The targetless check of ``headalign check``.

    Refits the right camera's rotation relative to the left (pitch, yaw, roll) on the
    pairs' own stereo matches with the intrinsics and lenses held, and judges the change
    by the depth error it causes at 5 m (docs/check.md).

    Args:
        views: as in :func:`calibrate` (a path, or a list of ``(left, right)`` ``uint8``
            arrays of one rig), natural scenes, no target needed.
        calibration: a :class:`Calibration`, or the path of a calibration file
            (headalign's ``calibration.json``, an OpenCV stereo YAML ``M1 D1 M2 D2 R T``, a
            Kalibr ``camchain.yaml``).
        baseline_m: the baseline in metres, for a calibration whose ``T`` is in baselines.
        corners: corners detected per image (default 1500).
        seed: seed of the RANSAC.
        significance: a change is significant at this many sigmas.
        depth_limit_pct: the depth error at 5 m that asks for recalibration, percent.
        progress: as in :func:`calibrate`.

    Returns:
        The :class:`CheckReport`: ``verdict`` (``good``, ``can-improve``,
        ``recalibrate``), ``conclusive``, the rotation change and its sigmas, ``updated``
        (the calibration with the refitted rotation, when the refit validates) and the
        whole ``report``.

    Raises:
        ValueError: bad input (images, options, a calibration in baselines without
            ``baseline_m``, a calibration of another image size).
        RuntimeError: too few matches survive.
    """
    if not isinstance(calibration, Calibration):
        calibration = os.fsdecode(calibration)
    return _headalign.check(
        _as_views(views),
        calibration,
        baseline_m,
        corners,
        seed,
        significance,
        depth_limit_pct,
        _progress_callback(progress),
    )
