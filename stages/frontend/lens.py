"""Camera models: what ``--intrinsics`` (and the ``intrinsics.txt`` the product reads) say about the
lens, whether the values describe a camera at all (:func:`check_camera`, run at ingest), and the
undistortion maps ingest applies to every frame.

Syntax (the option and the file alike; numbers separated by commas or spaces, source pixels,
pixel-centre convention: (0, 0) is the centre of the top-left pixel):

    fx fy cx cy                                 PINHOLE
    fx fy cx cy k1 k2 p1 p2                     OPENCV: OpenCV's radial-tangential model
    fx fy cx cy k1 k2 p1 p2 k3                  (cv2.undistort's 4 / 5 coefficients)
    OPENCV_FISHEYE fx fy cx cy k1 k2 k3 k4      OpenCV's fisheye model (cv2.fisheye)

A model name (COLMAP's: ``PINHOLE``, ``OPENCV``, ``OPENCV_FISHEYE``; case-insensitive; ``fisheye``
for short) may lead the numbers, followed by a space or a colon
(``--intrinsics fisheye:285,285,320,240,0.05,0.01,0,0``). Nine numbers without a name are a 3x3
matrix (row-major) when they end with ``0 0 1``, else OPENCV with k3. OPENCV with every
coefficient zero is PINHOLE (nothing to undistort); a trailing k3 = 0 is dropped.

The models, on normalised coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), r^2 = x^2 + y^2:
OPENCV  x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2), y_d likewise;
OPENCV_FISHEYE  theta = atan(r), theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
k4 theta^8), (x_d, y_d) = theta_d / r (x, y). Ingest undistorts each frame to the pinhole camera
of the same fx, fy, cx, cy: output pixel (u, v) samples the source where the model sends it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
_ALIASES = {"pinhole": "PINHOLE", "opencv": "OPENCV", "opencv_fisheye": "OPENCV_FISHEYE", "fisheye": "OPENCV_FISHEYE"}
COEFF_NAMES = {"PINHOLE": (), "OPENCV": ("k1", "k2", "p1", "p2", "k3"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}
SYNTAX = ("fx,fy,cx,cy (PINHOLE), fx,fy,cx,cy,k1,k2,p1,p2[,k3] (OPENCV) or "
          "OPENCV_FISHEYE:fx,fy,cx,cy,k1,k2,k3,k4")

# Plausibility (check_camera). Field of view over the image width / height, degrees: a pinhole
# image cannot reach 180; a fisheye image can (equidistant estimate n / f rad).
FOV_DEG = {"PINHOLE": (5.0, 170.0), "OPENCV": (5.0, 170.0), "OPENCV_FISHEYE": (5.0, 250.0)}
MAX_ASPECT = 3.0  # fx / fy within [1/3, 3]: anamorphic 2x squeeze is the most a real camera has
MAX_EMPTY = 0.5  # at most this share of the undistorted image may fall outside the source frame


@dataclass(frozen=True)
class Camera:
    """A camera at the source resolution: pinhole intrinsics (px) and its lens distortion."""

    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "PINHOLE"
    coeffs: tuple[float, ...] = ()

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def distorted(self) -> bool:
        """Whether ingest undistorts the frames (every model but PINHOLE)."""
        return self.model != "PINHOLE"

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def coeff_text(self, nonzero: bool = False) -> str:
        """'k1=-0.28, k2=0.08, ...' (``nonzero``: only the coefficients that are not 0)."""
        pairs = [(n, v) for n, v in zip(COEFF_NAMES[self.model], self.coeffs) if v or not nonzero]
        if not pairs:
            return "the fisheye projection" if self.model == "OPENCV_FISHEYE" else "no distortion"
        return ", ".join(f"{n}={v:g}" for n, v in pairs)

    def describe(self) -> str:
        return self.model if not self.distorted else f"{self.model} {self.coeff_text()}"


def make_camera(intrinsics: tuple[float, ...], model: str = "PINHOLE", coeffs: tuple[float, ...] = ()) -> Camera:
    """The canonical Camera: OPENCV without a non-zero coefficient is PINHOLE, a trailing k3 = 0 goes."""
    coeffs = tuple(float(v) for v in coeffs)
    if model == "OPENCV":
        if not any(coeffs):
            model, coeffs = "PINHOLE", ()
        elif len(coeffs) == 5 and coeffs[4] == 0:
            coeffs = coeffs[:4]
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return Camera(fx, fy, cx, cy, model, coeffs)


def _split(text: str) -> tuple[str | None, list[str]]:
    """'[MODEL][: ]numbers' -> (model name as written or None, number tokens)."""
    s = text.strip()
    head, sep, rest = s.partition(":")
    if sep and _is_name(head.strip()):
        s = head + " " + rest
    tokens = s.replace(",", " ").split()
    if tokens and _is_name(tokens[0]):
        return tokens[0], tokens[1:]
    return None, tokens


def _is_name(t: str) -> bool:
    """A model name: letters and '_' that are not a number ('nan', 'inf' are numbers)."""
    return t.replace("_", "").isalpha() and not _is_float(t)


def _model_of(name: str | None, n: int, vals: list[float]) -> str:
    if name is not None:
        model = _ALIASES.get(name.lower())
        if model is None:
            raise ValueError(f"unknown camera model {name!r} (accepted: {', '.join(MODELS)})")
        counts = {"PINHOLE": (4,), "OPENCV": (8, 9), "OPENCV_FISHEYE": (8,)}[model]
        if n not in counts:
            raise ValueError(f"{model} takes {' or '.join(map(str, counts))} numbers, got {n}; expected {SYNTAX}")
        return model
    if n == 4:
        return "PINHOLE"
    if n == 8 or (n == 9 and vals[6:] != [0.0, 0.0, 1.0]):
        return "OPENCV"
    if n == 9:
        return "MATRIX"
    raise ValueError(f"expected {SYNTAX}, or a 3x3 matrix; got {n} numbers")


def parse_camera(text: str) -> Camera:
    """``--intrinsics`` / ``intrinsics.txt`` text -> Camera (module docstring); ValueError naming
    the problem (unknown model, count, not a number, non-finite, a focal length <= 0). Whether
    the values fit the image is :func:`check_camera`'s."""
    name, tokens = _split(text)
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise ValueError(f"{bad!r} is not a number; expected {SYNTAX}") from None
    model = _model_of(name, len(vals), vals)
    intr: tuple[float, float, float, float]
    if model == "MATRIX":
        intr, model, coeffs = (vals[0], vals[4], vals[2], vals[5]), "PINHOLE", []
    else:
        intr, coeffs = (vals[0], vals[1], vals[2], vals[3]), vals[4:]
    names = ("fx", "fy", "cx", "cy") + COEFF_NAMES[model]
    for n, v in zip(names, list(intr) + coeffs):
        if not math.isfinite(v):
            raise ValueError(f"{n}={v:g}: non-finite values (nan, inf) are not a camera")
    for n, v in zip(("fx", "fy"), intr[:2]):
        if v <= 0:
            raise ValueError(f"{n}={v:g}: focal lengths must be positive")
    return make_camera(intr, model, tuple(coeffs))


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------- the models


def radial(cam: Camera, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised radius r (M,) -> (r_d, d r_d / d r) of the model's radial part
    (the fisheye derivative is taken in theta = atan(r): the same sign)."""
    k = np.zeros(5)
    k[:len(cam.coeffs)] = cam.coeffs
    if cam.model == "OPENCV_FISHEYE":
        t = np.arctan(r)
        t2 = t * t
        poly = 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
        return t * poly, 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
    k1, k2, k3 = k[0], k[1], k[4]
    r2 = r * r
    poly = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return r * poly, 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))


def distort_normalized(cam: Camera, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates -> distorted ones (the model of the module docstring)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if cam.model == "PINHOLE":
        return x, y
    r = np.hypot(x, y)
    rd, _ = radial(cam, r)
    if cam.model == "OPENCV_FISHEYE":
        s = np.where(r > 0, rd / np.where(r > 0, r, 1.0), 1.0)
        return x * s, y * s
    p1, p2 = cam.coeffs[2], cam.coeffs[3]
    s = np.where(r > 0, rd / np.where(r > 0, r, 1.0), 1.0)
    r2 = r * r
    return (x * s + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * s + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def distort_pixels(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """Pixels (M, 2) of the undistorted (pinhole) image -> where the lens puts them in the source."""
    uv = np.asarray(uv, np.float64)
    xd, yd = distort_normalized(cam, (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy)
    return np.stack([xd * cam.fx + cam.cx, yd * cam.fy + cam.cy], -1)


def source_positions(cam: Camera, work_size: tuple[int, int], source_size: tuple[int, int]) -> np.ndarray:
    """Where each pixel of the undistorted frame at working resolution ``work_size`` = (w, h) was
    seen in the source frame of ``source_size`` = (W, H): float64 (h, w, 2) source pixels (x, y),
    pixel-centre convention (ingest undistorts at the source size, then resizes). Data registered
    to the source frame (a dataset's depth maps) is read at these positions to compare it with
    the run's maps."""
    (w, h), (sw, sh) = work_size, source_size
    u, v = np.meshgrid((np.arange(w) + 0.5) * (sw / w) - 0.5, (np.arange(h) + 0.5) * (sh / h) - 0.5)
    return distort_pixels(cam, np.stack([u.ravel(), v.ravel()], -1)).reshape(h, w, 2)


def undistort_maps(cam: Camera, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV remap maps float32 (h, w) x, y: output pixel of the pinhole camera of the same
    intrinsics -> its source position (size = (w, h) of the source)."""
    K = cam.K()
    if cam.model == "OPENCV_FISHEYE":
        mx, my = cv2.fisheye.initUndistortRectifyMap(K, np.asarray(cam.coeffs, np.float64), np.eye(3), K,
                                                     tuple(size), cv2.CV_32FC1)
        return mx, my
    mx, my = cv2.initUndistortRectifyMap(K, np.asarray(cam.coeffs, np.float64), None, K, tuple(size), cv2.CV_32FC1)
    return mx, my


def undistort_image(img: np.ndarray, cam: Camera, border: str = "replicate") -> np.ndarray:
    """A source image (H, W[, C]) seen through the lens -> the pinhole image of the same intrinsics
    (outside the source: its nearest edge pixel, ``border`` "replicate", or 0, "black"). Bicubic:
    the map stretches a fisheye's periphery by up to ~1.4x and bilinear blurs every pixel it
    samples between (a fisheye clip's depth AbsRel 1.11x the pinhole clip's with bilinear, 1.01x
    with bicubic, docs/log/2026-11-28-cams3.md)."""
    h, w = img.shape[:2]
    mx, my = undistort_maps(cam, (w, h))
    mode = cv2.BORDER_REPLICATE if border == "replicate" else cv2.BORDER_CONSTANT
    return cv2.remap(np.ascontiguousarray(img), mx, my, interpolation=cv2.INTER_CUBIC, borderMode=mode, borderValue=0)


# ----------------------------------------------------------------------------- plausibility


def check_camera(cam: Camera, size: tuple[int, int]) -> None:
    """ValueError naming the value when ``cam`` is no camera for frames of ``size`` = (w, h) px:
    a value not finite, a field of view outside FOV_DEG (fx over the width, fy over the height),
    a pixel aspect fx / fy beyond MAX_ASPECT, a principal point outside the image, or a
    distortion that does not map the undistorted image one-to-one into the frame (the radial
    mapping not increasing up to the farthest corner, the Jacobian of the full model not
    positive on a grid over the image, or more than MAX_EMPTY of the undistorted image falling
    outside the source frame)."""
    _check_cached(cam, (int(size[0]), int(size[1])))


@functools.lru_cache(maxsize=64)
def _check_cached(cam: Camera, size: tuple[int, int]) -> None:
    w, h = size
    names = ("fx", "fy", "cx", "cy") + COEFF_NAMES[cam.model]
    for n, v in zip(names, cam.intrinsics + cam.coeffs):
        if not math.isfinite(v):
            raise ValueError(f"{n}={v:g}: non-finite values (nan, inf) are not a camera")
    _check_focal(cam, w, h)
    for n, c, extent in (("cx", cam.cx, w), ("cy", cam.cy, h)):
        if not -0.5 <= c <= extent - 0.5:
            raise ValueError(f"{n}={c:g}: the principal point lies outside the {w}x{h} image "
                             f"({n} must be within -0.5..{extent - 0.5:g} px)")
    if cam.distorted:
        _check_distortion(cam, w, h)


def field_of_view(model: str, f: float, extent: int) -> float:
    """Degrees the image's ``extent`` px span at focal length f (fisheye: equidistant estimate)."""
    if model == "OPENCV_FISHEYE":
        return math.degrees(extent / f)
    return math.degrees(2.0 * math.atan(extent / (2.0 * f)))


def _check_focal(cam: Camera, w: int, h: int) -> None:
    lo, hi = FOV_DEG[cam.model]
    for n, f, extent, kind in (("fx", cam.fx, w, "horizontal"), ("fy", cam.fy, h, "vertical")):
        if not f > 0:
            raise ValueError(f"{n}={f:g}: focal lengths must be positive")
        fov = field_of_view(cam.model, f, extent)
        if not lo <= fov <= hi:
            raise ValueError(f"{n}={f:g}: a {kind} field of view of {fov:.3g} deg over {extent} px "
                             f"(a {cam.model} camera: {lo:g}-{hi:g} deg)")
    if not 1.0 / MAX_ASPECT <= cam.fx / cam.fy <= MAX_ASPECT:
        raise ValueError(f"fx={cam.fx:g}, fy={cam.fy:g}: a pixel aspect fx/fy of {cam.fx / cam.fy:.3g} "
                         f"(plausible: 1/{MAX_ASPECT:g}-{MAX_ASPECT:g})")


def _image_grid(w: int, h: int, n: int = 48) -> np.ndarray:
    """Pixels (M, 2) on a grid over the image, its edges and corners included."""
    u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, n + 1), np.linspace(-0.5, h - 0.5, max(2, n * h // max(w, 1)) + 1))
    return np.stack([u.ravel(), v.ravel()], -1)


def _check_distortion(cam: Camera, w: int, h: int) -> None:
    what = cam.coeff_text(nonzero=True)
    fold = "folds" if "," not in what else "fold"
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_max = float(np.max(np.hypot((corners[:, 0] - cam.cx) / cam.fx, (corners[:, 1] - cam.cy) / cam.fy)))
    r = np.linspace(0.0, r_max, 4001)
    with np.errstate(all="ignore"):
        rd, drd = radial(cam, r)
        if not (np.all(np.isfinite(rd)) and np.all(np.isfinite(drd))):
            raise ValueError(f"{what}: the distortion is not finite over the image")
        bad = np.flatnonzero(drd <= 0)
        if len(bad):
            raise ValueError(f"{what} {fold} the image (distortion not monotonic: it turns back at "
                             f"{r[bad[0]] / r_max:.2f} of the radius to the farthest corner)")
        grid = _image_grid(w, h)
        if cam.model == "OPENCV":
            det = _jacobian_det(cam, (grid[:, 0] - cam.cx) / cam.fx, (grid[:, 1] - cam.cy) / cam.fy)
            if not np.all(np.isfinite(det)):
                raise ValueError(f"{what}: the distortion overflows over the image")
            bad = np.flatnonzero(det <= 0)
            if len(bad):
                u, v = grid[bad[0]]
                raise ValueError(f"{what} {fold} the image (the distortion's Jacobian is not positive at "
                                 f"pixel {int(round(u))},{int(round(v))})")
        src = distort_pixels(cam, grid)
    inside = np.all(np.isfinite(src), axis=1) & (src[:, 0] >= -0.5) & (src[:, 0] <= w - 0.5) \
        & (src[:, 1] >= -0.5) & (src[:, 1] <= h - 0.5)
    empty = 1.0 - float(inside.mean())
    if empty > MAX_EMPTY:
        raise ValueError(f"{what}: {100 * empty:.0f} % of the undistorted image falls outside the frame "
                         f"(at most {100 * MAX_EMPTY:.0f} %: the distortion stretches the image beyond any lens)")


def _jacobian_det(cam: Camera, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """det d(x_d, y_d) / d(x, y) of the OPENCV model at normalised (x, y)."""
    k1, k2, p1, p2 = cam.coeffs[:4]
    k3 = cam.coeffs[4] if len(cam.coeffs) > 4 else 0.0
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2 * k2 + r2 * 3 * k3)  # d rad / d r^2
    dxx = rad + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x
    dyy = rad + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x
    dxy = 2 * x * y * g + 2 * p1 * x + 2 * p2 * y
    return dxx * dyy - dxy * dxy
