"""Cameras as they come (issues 36, 37, 39): the OpenCV 5-coefficient and fisheye models at ingest,
the plausibility check that refuses values no lens has (for --intrinsics and intrinsics.txt
alike, one line naming the value, exit 2), the synthetic round trip through both models, and
number lists with a leading minus sign after --intrinsics / --distortion / --fisheye."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from conftest import cli

from gcvd_flow import pipeline
from gcvd_flow.cli import glue_negative_values
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.io import formats
from gcvd_flow.io.sources import open_source
from gcvd_flow.stages.frontend import lens
from gcvd_flow.stages.frontend.ingest import undistort_frame

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
ICL = "525,525,319.5,239.5"
TUM_FR1 = (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633)  # published, 640x480
GOPRO_FISHEYE = "OPENCV_FISHEYE:870,868,962.3,541.8,0.052,-0.018,0.012,-0.004"  # 1920x1080, ~120 deg wide

# (what, the values after the ICL focal lengths or in their place, a fragment of the error)
BAD = [("principal point outside", "525,525,700,239.5", "cx=700"),
       ("k1=-5", ICL + ",-5,0,0,0", "k1=-5 folds the image"),
       ("k1=10", ICL + ",10,0,0,0", "k1=10"),
       ("k1=1e300", ICL + ",1e300,0,0,0", "k1=1e+300"),
       ("p1=p2=5", ICL + ",0,0,5,5", "p1=5, p2=5 fold the image"),
       ("fx=1e-30", "1e-30,525,319.5,239.5", "fx=1e-30"),
       ("fx=1e30", "1e30,525,319.5,239.5", "fx=1e+30"),
       ("fisheye k1=-5", "OPENCV_FISHEYE:" + ICL + ",-5,0,0,0", "k1=-5 folds the image")]


def _black_clip(root: Path, size: tuple[int, int] = (640, 480), intrinsics: str | None = None) -> Path:
    """A generic-layout folder of two black frames (open_source reads only the first frame's size)."""
    (root / "frames").mkdir(parents=True)
    for i in range(2):
        formats.write_rgb_png(root / "frames" / f"{i:06d}.png", np.zeros((size[1], size[0], 3), np.uint8))
    if intrinsics is not None:
        (root / "intrinsics.txt").write_text(intrinsics + "\n")
    return root


def _open(path: Path, intrinsics: str | None = None):
    cfg = pipeline.GCVDConfig(ingest={"intrinsics": intrinsics} if intrinsics else {})
    return pipeline.open_source(str(path), cfg), cfg


# ------------------------------------------------------------------------------ plausibility


@pytest.mark.parametrize("what, text, fragment", BAD, ids=[b[0] for b in BAD])
def test_values_no_lens_has_are_refused_for_the_option_and_the_file(tmp_path, what, text, fragment):
    clip = _black_clip(tmp_path / "opt")
    with pytest.raises(UsageError) as ei:
        _open(clip, text)
    msg = str(ei.value)
    assert msg.startswith("--intrinsics: ") and fragment in msg and "\n" not in msg, msg
    filed = _black_clip(tmp_path / "file", intrinsics=text.replace(":", " ").replace(",", " "))
    with pytest.raises(UsageError) as ei:
        _open(filed)
    msg = str(ei.value)
    assert msg.startswith(str(filed / "intrinsics.txt")) and fragment in msg and "\n" not in msg, msg


def test_the_cli_says_it_in_one_line_with_exit_2(tmp_path):
    clip = _black_clip(tmp_path / "c")
    p = cli("plan", str(clip), "--out", str(tmp_path / "r"), "--cache", str(tmp_path / "cache"),
            "--intrinsics", ICL + ",-5,0,0,0")
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1 and "--intrinsics: k1=-5 folds the image" in err[0], p.stderr
    (clip / "intrinsics.txt").write_text("525 525 319.5 239.5 0 0 5 5\n")
    p = cli("plan", str(clip), "--out", str(tmp_path / "r"), "--cache", str(tmp_path / "cache"))
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1 and "intrinsics.txt: p1=5, p2=5" in err[0], p.stderr


@pytest.mark.parametrize("text, size", [
    (ICL, (640, 480)),
    (",".join(map(str, TUM_FR1)), (640, 480)),
    ("OPENCV:" + ",".join(map(str, TUM_FR1)), (640, 480)),
    ("984.2,980.8,690,233.2,-0.372,0.2,0.0022,0.00138,-0.0728", (1392, 512)),  # KITTI raw colour camera
    ("458.654,457.296,367.215,248.375,-0.2834,0.0740,0.00019,0.0000176", (752, 480)),  # EuRoC cam0
    (GOPRO_FISHEYE, (1920, 1080)),
    ("fisheye:285.7,285.9,418.9,404.5,-0.0063,0.0417,-0.0392,0.0065", (848, 800)),  # T265-like, 163 deg
], ids=["icl", "tum-fr1", "tum-fr1-named", "kitti-raw", "euroc", "gopro-fisheye", "t265-fisheye"])
def test_real_cameras_pass(text, size):
    lens.check_camera(lens.parse_camera(text), size)


@pytest.mark.parametrize("name", ["hololens_walk_100_199", "kitti07_first100"])
def test_the_shared_real_clips_pass(name):
    root = SHARED / name
    if not (root / "intrinsics.txt").exists():
        pytest.skip(f"{root} not present")
    src, cfg = _open(root)
    cam = pipeline._ingest_summary(SimpleNamespace(source=src), cfg.ingest)
    assert not cam["guessed"] and "distortion" not in cam


def test_tum_fr1_full_calibration_is_accepted_as_typed(tmp_path):
    """Issue 37's held-out TUM run: the published Kinect calibration, k3 included, typed after
    --intrinsics and written in intrinsics.txt, opens (exit 0) as a 5-coefficient OPENCV camera;
    its radial map increases well past the farthest corner (no fold to clip)."""
    typed = ",".join(map(str, TUM_FR1))
    clip = _black_clip(tmp_path / "c")
    p = cli("plan", str(clip), "--out", str(tmp_path / "r"), "--cache", str(tmp_path / "cache"), "--intrinsics", typed)
    assert p.returncode == 0, p.stderr
    (clip / "intrinsics.txt").write_text(" ".join(map(str, TUM_FR1)) + "\n")
    p = cli("plan", str(clip), "--out", str(tmp_path / "r2"), "--cache", str(tmp_path / "cache"))
    assert p.returncode == 0, p.stderr
    src, _ = _open(clip)
    assert (src.distortion_model, tuple(src.distortion)) == ("OPENCV", TUM_FR1[4:])
    cam = lens.parse_camera(typed)
    r = np.linspace(0.0, 1.5, 1501)  # the farthest corner is at r = 0.79
    assert np.all(np.diff(lens.radial(cam, r)[0]) > 0)


def test_tum_fr1_undistortion_agrees_with_cv2_undistort_points():
    """For source pixels on a grid over the 640x480 frame, OpenCV's iterated undistortPoints gives
    the pinhole pixel; ingest's undistortion map at that pixel points back to the source pixel
    (within 0.01 px; the float32 maps), over the whole frame but its corners."""
    cam = lens.parse_camera(",".join(map(str, TUM_FR1)))
    u, v = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    src = np.stack([u.ravel(), v.ravel()], -1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    pin = cv2.undistortPoints(src[:, None, :], cam.K(), np.asarray(cam.coeffs), R=None, P=cam.K(),
                              criteria=crit).reshape(-1, 2)
    inside = (pin[:, 0] >= 0) & (pin[:, 0] <= 639) & (pin[:, 1] >= 0) & (pin[:, 1] <= 479)
    assert inside.mean() > 0.95
    mx, my = lens.undistort_maps(cam, (640, 480))
    q = pin[inside].astype(np.float32)[None]
    at = np.stack([cv2.remap(m, q[..., 0], q[..., 1], cv2.INTER_LINEAR).ravel() for m in (mx, my)], -1)
    err = np.abs(at - src[inside]).max()
    assert err < 0.01, err
    assert np.abs(pin - src).max() > 15  # the lens moves the periphery by over 15 px


def test_tum_calibration_without_its_k3_folds_the_image():
    # what issue 37 ran: the published fr1 coefficients with k3 dropped turn back near the corners
    with pytest.raises(ValueError, match="fold the image .* 0.9"):
        lens.check_camera(lens.parse_camera(",".join(map(str, TUM_FR1[:8]))), (640, 480))


# ------------------------------------------------------------------------------ syntax


@pytest.mark.parametrize("text, model, coeffs", [
    ("500 500 320 240", "PINHOLE", ()),
    ("500 500 320 240 -0.28 0.08 0.001 -0.0005", "OPENCV", (-0.28, 0.08, 0.001, -0.0005)),
    ("500 500 320 240 -0.28 0.08 0.001 -0.0005 0.02", "OPENCV", (-0.28, 0.08, 0.001, -0.0005, 0.02)),
    ("500 500 320 240 -0.28 0.08 0.001 -0.0005 0", "OPENCV", (-0.28, 0.08, 0.001, -0.0005)),
    ("OPENCV 500 500 320 240 0 0 0 0", "PINHOLE", ()),
    ("OPENCV_FISHEYE 500 500 320 240 0.05 -0.01 0 0", "OPENCV_FISHEYE", (0.05, -0.01, 0.0, 0.0)),
    ("fisheye:500,500,320,240,0,0,0,0", "OPENCV_FISHEYE", (0.0, 0.0, 0.0, 0.0)),
    ("500 0 320\n0 500 240\n0 0 1", "PINHOLE", ()),
])
def test_the_option_and_the_file_read_the_same_camera(tmp_path, text, model, coeffs):
    cam = lens.parse_camera(text.replace("\n", " "))
    assert (cam.model, cam.coeffs, cam.intrinsics) == (model, coeffs, (500.0, 500.0, 320.0, 240.0))
    f = tmp_path / "intrinsics.txt"
    f.write_text(text + "\n")
    src = open_source(str(_black_clip(tmp_path / "c", intrinsics=text)))
    filed = lens.make_camera(src.intrinsics, src.distortion_model if src.distortion else "PINHOLE", src.distortion or ())
    assert filed == cam
    K, _, _ = formats.read_camera_txt(f)
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == cam.intrinsics


@pytest.mark.parametrize("text, fragment", [("FULL_OPENCV 1 1 1 1 0 0 0 0", "unknown camera model"),
                                            ("OPENCV_FISHEYE 500 500 320 240 0.1", "takes 8"),
                                            ("500 500 320 240 0.1", "k1,k2,p1,p2"),
                                            ("500 500 320 240 x 0 0 0", "'x' is not a number")])
def test_malformed_camera_text(text, fragment):
    with pytest.raises(ValueError, match=fragment):
        lens.parse_camera(text)


def test_written_intrinsics_txt_reads_back(tmp_path):
    K = np.array([[200.0, 0, 127.5], [0, 201.0, 95.5], [0, 0, 1]])
    for dist, model in [((-0.28, 0.08, 0.001, -0.0005), "OPENCV"), ((-0.28, 0.08, 0.001, -0.0005, 0.02), "OPENCV"),
                        ((0.05, -0.01, 0.002, -0.0003), "OPENCV_FISHEYE")]:
        formats.write_intrinsics_txt(tmp_path / "i.txt", K, dist, model)
        K2, m2, c2 = formats.read_camera_txt(tmp_path / "i.txt")
        assert m2 == model and np.allclose(c2, dist) and np.allclose(K2, K)
        assert len((tmp_path / "i.txt").read_text().split()) == 4 + len(dist) + (model != "OPENCV" or len(dist) == 5)


# ------------------------------------------------------------------------------ the models against OpenCV


def _cv2_project(cam: lens.Camera, xy: np.ndarray) -> np.ndarray:
    """OpenCV's own projection of normalised points (M, 2) through the camera -> pixels (M, 2)."""
    obj = np.concatenate([xy, np.ones((len(xy), 1))], 1)[:, None, :]
    D = np.asarray(cam.coeffs, np.float64)
    if cam.model == "OPENCV_FISHEYE":
        out, _ = cv2.fisheye.projectPoints(obj, np.zeros((3, 1)), np.zeros((3, 1)), cam.K(), D)
    else:
        out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), cam.K(), D)
    return out.reshape(-1, 2)


CAMS = {"opencv5": lens.parse_camera(",".join(str(v / 2 if i < 4 else v) for i, v in enumerate(TUM_FR1))),
        "fisheye": lens.parse_camera("OPENCV_FISHEYE:150,150,160.3,119.6,0.05,-0.02,0.01,-0.004")}


@pytest.mark.parametrize("name", list(CAMS))
def test_the_model_is_opencvs(name):
    cam = CAMS[name]
    uv = lens._image_grid(320, 240, 16)
    xy = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy], -1)
    np.testing.assert_allclose(lens.distort_pixels(cam, uv), _cv2_project(cam, xy), atol=1e-7)


def _blobs(centres: np.ndarray, size: tuple[int, int], sigma: float = 1.2) -> np.ndarray:
    """uint8 (h, w, 3): Gaussian dots at sub-pixel ``centres`` (M, 2) (pixel-centre convention)."""
    w, h = size
    img = np.zeros((h, w))
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    for cu, cv in centres:
        img += np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma ** 2))
    return np.repeat(np.clip(np.round(img * 250), 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _centroids(img: np.ndarray, near: np.ndarray, r: int = 4) -> np.ndarray:
    g = img[..., 0].astype(np.float64)
    out = []
    for cu, cv in near:
        u0, v0 = int(round(cu)), int(round(cv))
        win = g[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
        vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
        out.append([(win * uu).sum() / win.sum(), (win * vv).sum() / win.sum()])
    return np.array(out)


@pytest.mark.parametrize("name", list(CAMS))
def test_ingest_undistortion_puts_points_where_opencv_projects_them(name):
    """Dots drawn where OpenCV projects known rays through the lens land, after ingest's
    undistortion, at those rays' pinhole pixels (within 0.1 px); without it they are pixels off."""
    cam = CAMS[name]
    u, v = np.meshgrid(np.linspace(40, 280, 7), np.linspace(30, 210, 5))
    pin = np.stack([u.ravel(), v.ravel()], -1)  # pinhole pixels of the rays
    xy = np.stack([(pin[:, 0] - cam.cx) / cam.fx, (pin[:, 1] - cam.cy) / cam.fy], -1)
    src = _blobs(_cv2_project(cam, xy), (320, 240))
    und = undistort_frame(src, cam.intrinsics, cam.coeffs, cam.model)
    err = np.linalg.norm(_centroids(und, pin) - pin, axis=1)
    assert err.max() < 0.1, err.max()
    far = np.linalg.norm(pin - [cam.cx, cam.cy], axis=1) > 100
    assert np.median(np.linalg.norm(_cv2_project(cam, xy) - pin, axis=1)[far]) > 2.0  # the lens matters


# ------------------------------------------------------------------------------ synth round trip

ROUND_TRIP = {"opencv5": ((-0.25, 0.08, 0.001, -0.0008, -0.02), "OPENCV"),
              "fisheye": ((0.03, -0.01, 0.004, -0.001), "OPENCV_FISHEYE")}


def _median_flow(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    f = dis.calc(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b, cv2.COLOR_RGB2GRAY), None)
    return float(np.median(np.linalg.norm(f, axis=-1)[mask]))


@pytest.mark.parametrize("name", list(ROUND_TRIP))
def test_synth_round_trip_reproduces_the_pinhole_geometry(tmp_path, name):
    """A clip rendered through the lens, written with its intrinsics.txt and read back through
    ingest, is the pinhole clip: the flow between them is under 0.2 px (the distorted frames:
    several px)."""
    dist, model = ROUND_TRIP[name]
    size = (192, 144)
    d = render_clip(2, "loop", size=size, distortion=dist, distortion_model=model)
    p = render_clip(2, "loop", size=size)
    assert np.array_equal(d.K, p.K)  # (the depth is registered to the distorted frames: test_distortion.py)
    formats.write_generic_layout(tmp_path / "clip", d)
    assert (tmp_path / "clip" / "intrinsics.txt").read_text().startswith("OPENCV")
    src, cfg = _open(tmp_path / "clip")
    assert (src.distortion_model, src.distortion) == (model, pytest.approx(dist))
    it = pipeline._ingest_items(SimpleNamespace(source=src), cfg.ingest)[1]
    assert it["undistort"].value[1:] == [pytest.approx(list(dist)), model]  # in the item's key
    img = pipeline.run_ingest({"frame": it["frame"].loader(), "source_size": it["source_size"].value,
                               "name": "f", "undistort": it["undistort"].value}, cfg.ingest, None)["image"]
    m = np.zeros(size[::-1], bool)
    m[12:-12, 12:-12] = True
    m &= img.sum(-1) > 0
    assert m.mean() > 0.6
    assert _median_flow(img, p.frames[1], m) < 0.2
    assert _median_flow(d.frames[1], p.frames[1], m) > 1.5


def test_the_ingest_key_follows_the_model(tmp_path):
    same = "150,150,95.5,71.5,0.01,0.002,0,0"
    src = open_source(str(_black_clip(tmp_path / "c", (192, 144))))
    keys = []
    for text in (same, "OPENCV_FISHEYE:" + same):
        cfg = pipeline.GCVDConfig(ingest={"intrinsics": text})
        item = pipeline._ingest_items(SimpleNamespace(source=src), cfg.ingest)[0]
        keys.append(item["undistort"].value)
    assert keys[0][:2] == keys[1][:2] and keys[0][2] == "OPENCV" and keys[1][2] == "OPENCV_FISHEYE"
    files = []
    for text in (same, "OPENCV_FISHEYE " + same):
        (tmp_path / "c" / "intrinsics.txt").write_text(text.replace(",", " ") + "\n")
        files.append(open_source(str(tmp_path / "c")).digest)
    assert files[0] != files[1]


# ------------------------------------------------------------------------------ negative values in argv


def test_glue_negative_values():
    assert glue_negative_values(["synth", "o", "--distortion", "-0.28,0.09,0,0", "--frames", "3"]) == \
        ["synth", "o", "--distortion=-0.28,0.09,0,0", "--frames", "3"]
    assert glue_negative_values(["run", "x", "--intrinsics", "-.5,1,2,3"]) == ["run", "x", "--intrinsics=-.5,1,2,3"]
    # another option after it, '--' and other options' values are left alone
    assert glue_negative_values(["synth", "--distortion", "--frames", "3"]) == ["synth", "--distortion", "--frames", "3"]
    assert glue_negative_values(["--", "--fisheye", "-1"]) == ["--", "--fisheye", "-1"]
    assert glue_negative_values(["--seed", "-3"]) == ["--seed", "-3"]


def test_negative_first_coefficient_is_accepted_as_typed(tmp_path):
    r = cli("synth", str(tmp_path / "a"), "--frames", "2", "--size", "64x48", "--distortion", "-0.28,0.09,0,0,-0.01")
    assert r.returncode == 0, r.stderr
    _, model, coeffs = formats.read_camera_txt(tmp_path / "a" / "intrinsics.txt")
    assert model == "OPENCV" and coeffs == pytest.approx((-0.28, 0.09, 0, 0, -0.01))
    r = cli("synth", str(tmp_path / "b"), "--frames", "2", "--size", "64x48", "--fisheye", "-0.02,0.01,0,0")
    assert r.returncode == 0, r.stderr
    assert formats.read_camera_txt(tmp_path / "b" / "intrinsics.txt")[1:] == ("OPENCV_FISHEYE", (-0.02, 0.01, 0, 0))
    # --intrinsics with a leading minus: read as the option's value (and refused for what it says)
    p = cli("plan", str(tmp_path / "a"), "--out", str(tmp_path / "r"), "--cache", str(tmp_path / "cache"),
            "--intrinsics", "-50,50,31.5,23.5")
    assert p.returncode == 2 and "fx=-50" in p.stderr and "expected one argument" not in p.stderr, p.stderr


def test_the_undistorted_border_repeats_the_frame_edge_not_black():
    """Where the lens leaves the undistorted image's corners outside the frame (TUM fr1's, 5.6 % of
    the image), ingest fills them with the nearest edge pixel, not black: a hard black edge fixed
    in the image is a static feature for the flow and the depth prior (its synthetic clip: ATE
    2.5x the pinhole clip with black corners, 0.7x with the edge repeated; docs/log/2026-11-28-cams2.md).
    The corners are left out of every loss all the same (tests/test_user_masks.py)."""
    cam = lens.parse_camera("206.9,206.9,127.5,95.5,0.2624,-0.9531,-0.0054,0.0026,1.1633")
    frame = np.full((192, 256, 3), 128, np.uint8)
    frame[:, :128] = 60
    und = undistort_frame(frame, cam.intrinsics, cam.coeffs, cam.model)
    mx, my = lens.undistort_maps(cam, (256, 192))
    outside = (mx < -0.5) | (mx > 255.5) | (my < -0.5) | (my > 191.5)
    assert outside.mean() > 0.03
    assert und.min() >= 59 and und[outside].min() >= 59  # no black anywhere
    assert np.all(und[:10, :10] == 60) and np.all(und[-10:, -10:] == 128)  # each corner: its own edge


def test_the_guessed_camera_has_square_source_pixels():
    """Without intrinsics the guess f = 300/384 x long side holds in the source's (square) pixels:
    a 540x360 frame at 256x170 is resized by 0.4 % more in y, so fy = fx x sy / sx."""
    from gcvd_flow.stages.frontend.ingest import make_camera

    cam = make_camera(540, 360, 256, 170, None)
    K = np.asarray(cam["K"])
    assert cam["guessed"] and K[1, 1] / K[0, 0] == pytest.approx((170 / 360) / (256 / 540))
