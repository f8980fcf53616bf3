"""Type stubs of headalign (the docstrings are in __init__.py and the extension module)."""

import os
import pathlib
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str

PathLike = Union[str, "os.PathLike[str]"]
ProgressCallback = Callable[[str, str, int, int], Any]
ImagePair = Tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]

class Calibration:
    """A calibrated stereo pair in OpenCV's conventions (x_right = R x_left + T)."""

    @property
    def K1(self) -> npt.NDArray[np.float64]: ...
    @property
    def D1(self) -> npt.NDArray[np.float64]: ...
    @property
    def K2(self) -> npt.NDArray[np.float64]: ...
    @property
    def D2(self) -> npt.NDArray[np.float64]: ...
    @property
    def R(self) -> npt.NDArray[np.float64]: ...
    @property
    def T(self) -> npt.NDArray[np.float64]: ...
    @property
    def image_size(self) -> Tuple[int, int]: ...
    @property
    def lens(self) -> str: ...
    @property
    def lens_model(self) -> Optional[str]: ...
    @property
    def translation_unit(self) -> str: ...
    @property
    def sigmas(self) -> Dict[str, float]: ...
    @property
    def covariance(self) -> npt.NDArray[np.float64]: ...
    @property
    def covariance_names(self) -> List[str]: ...
    @property
    def warnings(self) -> List[str]: ...
    @property
    def report(self) -> Optional[Dict[str, Any]]: ...
    def write(self, dir: PathLike) -> List[pathlib.Path]: ...

class Alignment:
    """The verge/tilt alignment of a head: aligned readings (degrees) and their sigmas."""

    @property
    def route(self) -> str: ...
    @property
    def reference(self) -> Dict[str, float]: ...
    @property
    def aligned_readings(self) -> Dict[str, float]: ...
    @property
    def sigmas(self) -> Dict[str, float]: ...
    @property
    def fixation_px(self) -> Tuple[Tuple[float, float], Tuple[float, float]]: ...
    @property
    def fixation_sigma_px(self) -> Optional[Tuple[Tuple[float, float], Tuple[float, float]]]: ...
    @property
    def verge_axes_measured(self) -> bool: ...
    @property
    def K1(self) -> npt.NDArray[np.float64]: ...
    @property
    def K2(self) -> npt.NDArray[np.float64]: ...
    @property
    def calibration(self) -> Optional[Calibration]: ...
    @property
    def undetermined(self) -> List[str]: ...
    @property
    def warnings(self) -> List[str]: ...

class CheckReport:
    """The result of :func:`check`: a verdict on a given calibration."""

    @property
    def verdict(self) -> str: ...
    @property
    def conclusive(self) -> bool: ...
    @property
    def rotation_change_deg(self) -> Dict[str, float]: ...
    @property
    def rotation_change_sigma_deg(self) -> Dict[str, float]: ...
    @property
    def updated(self) -> Optional[Calibration]: ...
    @property
    def update_refused(self) -> Optional[str]: ...
    @property
    def report(self) -> Dict[str, Any]: ...

def calibrate(
    views: Union[PathLike, Sequence[ImagePair]],
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
    progress: Union[bool, ProgressCallback] = False,
) -> Calibration:
    """Self-calibrate a stereo rig from views related by rigid motions of the whole rig."""
    ...

def align(
    session: PathLike,
    *,
    lens: Optional[str] = None,
    lens_terms: Optional[str] = None,
    baseline_m: Optional[float] = None,
    progress: Union[bool, ProgressCallback] = False,
) -> Alignment:
    """The verge/tilt alignment of a recorded head run."""
    ...

def read_image(path: PathLike) -> npt.NDArray[np.uint8]:
    """Read a PNG or JPEG file as a grey uint8 array of shape (height, width)."""
    ...

def check(
    views: Union[PathLike, Sequence[ImagePair]],
    calibration: Union[Calibration, PathLike],
    *,
    baseline_m: Optional[float] = None,
    corners: Optional[int] = None,
    seed: int = 0,
    significance: float = 5.0,
    depth_limit_pct: float = 1.0,
    progress: Union[bool, ProgressCallback] = False,
) -> CheckReport:
    """Check a given stereo calibration against stereo pairs of natural scenes."""
    ...

def read_calibration(path: PathLike) -> Calibration:
    """Read a calibration file: headalign JSON, OpenCV stereo YAML or Kalibr camchain."""
    ...
