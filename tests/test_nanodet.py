"""``--detector nanodet``: pre- and post-processing as pure functions on synthetic inputs, the depth masks, and the
bad-model-file paths through the CLI (one line naming the file, exit 2, nothing written). The real model and real
frames: tests/test_real_ccm.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from massviz.detect import nanodet as N
from massviz.errors import WeightsError

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "cup_handover"
CUP80 = 41


def test_preprocess_letterboxes_and_normalises_bgr():
    rgb = np.zeros((720, 1280, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50  # R, G, B
    blob = N.preprocess([rgb, rgb])
    assert blob.shape == (2, 3, 416, 416) and blob.dtype == np.float32
    top = (416 - int(720 * 416 / 1280)) // 2  # 234 rows of content, centred
    content = [(50 - N.MEAN[0]) / N.STD[0], (100 - N.MEAN[1]) / N.STD[1], (200 - N.MEAN[2]) / N.STD[2]]  # B, G, R
    pad = [-m / s for m, s in zip(N.MEAN, N.STD, strict=False)]
    for c in range(3):
        assert blob[0, c, 208, 208] == pytest.approx(content[c], abs=1e-4)
        assert blob[0, c, top + 1, 3] == pytest.approx(content[c], abs=1e-4)
        assert blob[0, c, top - 1, 208] == pytest.approx(pad[c], abs=1e-4)
        assert blob[0, c, 415, 0] == pytest.approx(pad[c], abs=1e-4)


def test_input_to_frame_inverts_the_letterbox():
    rw, rh = 416, int(720 * 416 / 1280)
    top = (416 - rh) // 2
    out = N.input_to_frame(np.array([[0, top, rw, top + rh], [104, top + rh / 2, 208, 416]]), 1280, 720)
    np.testing.assert_allclose(out[0], [0, 0, 1280, 720], atol=1e-6)
    np.testing.assert_allclose(out[1], [320, 360, 640, 720], atol=1e-6)  # clipped at the bottom
    # a portrait frame pads left and right
    out = N.input_to_frame(np.array([[(416 - 234) // 2, 0, (416 - 234) // 2 + 234, 416]]), 720, 1280)
    np.testing.assert_allclose(out[0], [0, 0, 720, 1280], atol=1e-6)


def test_distribution_distances_are_softmax_expectations_times_stride():
    logits = np.full((2, 32), -50.0)
    for side, b in enumerate((3, 0, 7, 5)):
        logits[0, side * 8 + b] = 50.0  # one-hot bins 3, 0, 7, 5
    logits[1] = 0.0  # uniform: expectation 3.5
    d = N.distribution_distances(logits, 16)
    np.testing.assert_allclose(d[0], [48, 0, 112, 80], atol=1e-6)
    np.testing.assert_allclose(d[1], [56, 56, 56, 56], atol=1e-9)


def _maps(entries):
    """Score and box maps for strides 8, 16, 32 with ``entries``: (stride, cell, class80, score, (l, t, r, b) bins)."""
    scores = [np.zeros((int(np.ceil(416 / s)) ** 2, 80), np.float32) for s in N.STRIDES]
    boxes = [np.full((int(np.ceil(416 / s)) ** 2, 32), -50.0, np.float32) for s in N.STRIDES]
    for stride, cell, cls, score, bins in entries:
        i = N.STRIDES.index(stride)
        scores[i][cell, cls] = score
        boxes[i][cell] = -50.0
        for side, b in enumerate(bins):
            boxes[i][cell, side * 8 + b] = 50.0
    return scores, boxes


def test_decode_box_geometry_class_filter_strict_threshold_and_class_aware_nms():
    n16 = 26
    cell = 10 * n16 + 12  # row 10, column 12 of stride 16: centre (12*16+7.5, 10*16+7.5)
    cx, cy = 12 * 16 + 7.5, 10 * 16 + 7.5
    entries = [
        (16, cell, CUP80, 0.8, (2, 3, 4, 5)),          # the cup
        (16, cell + 1, CUP80, 0.6, (3, 3, 3, 5)),      # the same cup from the next cell: suppressed by NMS
        (16, cell + 1, 39, 0.5, (3, 3, 3, 5)),         # a bottle there: another class, kept (class-aware NMS)
        (16, cell + 5 * n16, 0, 0.99, (2, 2, 2, 2)),   # a person: not one of the paper's classes
        (8, 100, CUP80, 0.4, (1, 1, 1, 1)),            # score == threshold: dropped (score > threshold)
        (32, 50, 73, 0.41, (1, 1, 1, 1)),              # a book just above it: kept
    ]
    boxes, scores, classes = N.decode(*_maps(entries), threshold=0.4)
    assert list(classes) == [CUP80, 39, 73]
    np.testing.assert_allclose(scores, [0.8, 0.5, 0.41], rtol=1e-6)
    np.testing.assert_allclose(boxes[0], [cx - 32, cy - 48, cx + 64, cy + 80], atol=1e-6)
    bx, by = (50 % 13) * 32 + 15.5, (50 // 13) * 32 + 15.5
    np.testing.assert_allclose(boxes[2], [bx - 32, by - 32, bx + 32, by + 32], atol=1e-6)
    # a lower threshold lets the stride-8 cup through; nothing above 0.9 is left
    assert CUP80 in N.decode(*_maps(entries), threshold=0.39)[2][3:]
    assert len(N.decode(*_maps(entries), threshold=0.9)[0]) == 0


def test_check_outputs_refuses_another_layout():
    good = [np.zeros((1, n, c), np.float32) for c in (80, 32) for n in (2704, 676, 169)]
    s, b = N.check_outputs(list(reversed(good)), 1, "m.onnx")  # found by shape, whatever the order
    assert [x.shape for x in s] == [(1, 2704, 80), (1, 676, 80), (1, 169, 80)]
    assert [x.shape for x in b] == [(1, 2704, 32), (1, 676, 32), (1, 169, 32)]
    with pytest.raises(WeightsError, match=r"^m\.onnx: not OpenCV Zoo's NanoDet"):
        N.check_outputs(good[:5], 1, "m.onnx")
    with pytest.raises(WeightsError, match="m.onnx"):
        N.check_outputs([np.zeros((1, 3, 416, 416))], 1, "m.onnx")


def test_depth_mask_is_the_surface_at_the_box_centre():
    z = np.full((120, 100), 1500, np.uint16)  # the wall behind
    z[20:100, 30:70] = 750 + (np.arange(40) % 7).astype(np.uint16)  # the cup, a surface 750-756 mm
    z[110:120, 0:100] = 700  # the table edge in front: nearer than the cup, but not at the box's centre
    z[5:8, 90:93] = 300  # stray near pixels
    z[0:3, 0:3] = 752  # a speck at the cup's depth, not connected to it
    z[50:55, 40:45] = 0  # a dropout inside the cup: no depth, not in the mask
    box = (0, 0, 100, 120)
    mask = N.depth_mask(z, box)
    expect = np.zeros_like(mask)
    expect[20:100, 30:70] = True
    expect[50:55, 40:45] = False
    np.testing.assert_array_equal(mask, expect)
    # a hand at the cup's depth touching it joins it (depth cannot tell them apart)
    z[60:80, 70:85] = 760
    assert N.depth_mask(z, box)[60:80, 70:85].all()
    # too little depth: an empty mask (d becomes NaN; the detection is never chosen)
    assert not N.depth_mask(np.zeros((50, 50), np.uint16), (0, 0, 50, 50)).any()
    assert N.depth_mask(np.zeros((5, 5), np.uint16), (0, 0, 5, 0)).shape == (0, 5)


def mug_on_a_table(elevation_deg: float, *, radius=0.045, height=0.13, camera_height=0.45, f=600.0, w=640, h=480):
    """A ray-cast depth image (mm) of an open mug (a vertical cylinder) standing on a table, seen from
    ``elevation_deg`` above the horizontal, its outer wall's mask and its box (silhouette, inside included)."""
    th = np.radians(elevation_deg)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    dx, dy = (u - w / 2) / f, (v - h / 2) / f  # camera-frame ray with z = 1; world: x right, y up, z forward
    ray = np.stack([dx, -dy * np.cos(th) - np.sin(th), -dy * np.sin(th) + np.cos(th)], -1)
    cam_y, mug_z = camera_height, camera_height / np.tan(th)  # the mug at the image's centre
    down = np.minimum(ray[..., 1], -1e-9)
    table = np.where(ray[..., 1] < 0, -cam_y / down, np.inf)
    a = ray[..., 0] ** 2 + ray[..., 2] ** 2
    b = -2 * mug_z * ray[..., 2]
    disc = b * b - 4 * a * (mug_z ** 2 - radius ** 2)
    root = np.sqrt(np.maximum(disc, 0))
    near, far = (-b - root) / (2 * a), (-b + root) / (2 * a)
    wall = (disc > 0) & (cam_y + near * ray[..., 1] >= 0) & (cam_y + near * ray[..., 1] <= height)
    top = (height - cam_y) / down
    over = (ray[..., 0] * top) ** 2 + (ray[..., 2] * top - mug_z) ** 2 <= radius ** 2
    inside = np.where(cam_y + far * ray[..., 1] >= 0, far, -cam_y / down)  # the far inner wall or the bottom
    hit = np.where(wall, near, np.where(over & ~wall, inside, np.inf))
    z = np.minimum(table, hit) * 1000.0
    z += np.random.default_rng(0).normal(0, 1, z.shape) * 2.5 * (np.minimum(z, 4000) / 1000.0) ** 2  # stereo noise
    depth = np.where(np.isfinite(z) & (z < 4000), z, 0).round().astype(np.uint16)
    ys, xs = np.nonzero(hit < table)
    return depth, wall & (near < table), (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)


@pytest.mark.parametrize("elevation", [35, 50])
def test_depth_mask_follows_a_mug_seen_from_above_not_the_table_at_its_base(elevation):
    """Seen from above, the table in front of a mug is nearer than the mug: the nearest slab of the box held the
    table and the mug's lower part (IoU 0.47-0.58 with its wall, d 16-20 mm off). The mask is its whole wall."""
    depth, wall, (x1, y1, x2, y2) = mug_on_a_table(elevation)
    mask = N.depth_mask(depth, (x1, y1, x2, y2))
    truth = wall[y1:y2, x1:x2]
    assert (mask & truth).sum() / (mask | truth).sum() >= 0.9
    z = depth[y1:y2, x1:x2].astype(float)
    assert abs(z[mask].mean() - z[truth].mean()) <= 5
    rows = np.flatnonzero(mask.any(1))
    assert len(rows) >= 0.95 * len(np.flatnonzero(truth.any(1)))  # top to bottom, not its lower half
    assert not (mask & ~truth)[-3:].any()  # none of the table at its base


# ------------------------------------------------------------------------------------------ bad model files (CLI)
def _varint(n: int) -> bytes:
    out = b""
    while True:
        b, n = n & 0x7F, n >> 7
        out += bytes([b | (0x80 if n else 0)])
        if not n:
            return out


def _field(num: int, payload) -> bytes:
    if isinstance(payload, int):
        return _varint(num << 3) + _varint(payload)
    payload = payload.encode() if isinstance(payload, str) else payload
    return _varint(num << 3 | 2) + _varint(len(payload)) + payload


def relu_onnx() -> bytes:
    """A valid ONNX model (Relu, 1×3×416×416 in and out) written field by field: loads, but is not NanoDet."""
    dims = b"".join(_field(1, _field(1, d)) for d in (1, 3, 416, 416))
    vtype = _field(1, _field(1, 1) + _field(2, dims))  # tensor float, shape
    graph = (_field(1, _field(1, "x") + _field(2, "y") + _field(4, "Relu")) + _field(2, "g")
             + _field(11, _field(1, "x") + _field(2, vtype)) + _field(12, _field(1, "y") + _field(2, vtype)))
    return _field(1, 7) + _field(7, graph) + _field(8, _field(1, "") + _field(2, 13))


def _estimate(tmp_path, capsys, *extra):
    from massviz.cli import main

    out = tmp_path / "out.csv"
    code = main(["estimate", str(SAMPLE), "--out", str(out), "--detector", "nanodet", "--no-cache", "--quiet",
                 *extra])
    err = capsys.readouterr().err.strip().splitlines()
    return code, err, out


@pytest.mark.parametrize("kind", ["corrupt", "wrong-layout", "missing"])
def test_bad_model_file_one_line_exit_2_nothing_written(tmp_path, capsys, kind, shared_dir):
    model = tmp_path / f"{kind}.onnx"
    if kind == "corrupt":
        model.write_bytes(b"\x08\x07garbage, not a protobuf" * 20)
    elif kind == "wrong-layout":
        model.write_bytes(relu_onnx())
        import cv2

        assert cv2.dnn.readNet(str(model)).getUnconnectedOutLayersNames()  # it is a loadable model
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    code, err, out = _estimate(tmp_path, capsys, "--detector-weights", str(model), "--weights", str(weights))
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"massviz estimate: error: {model}: "), err
    assert {"corrupt": "not a NanoDet ONNX model", "wrong-layout": "not OpenCV Zoo's NanoDet",
            "missing": "not found"}[kind] in err[0]
    assert not out.exists() and not any(p.name.startswith("out") for p in tmp_path.iterdir())


def test_checksum_mismatch_of_the_download_one_line_exit_2_nothing_kept(tmp_path, capsys, monkeypatch, shared_dir):
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    (mirror / N.NANODET_NAME).write_bytes(relu_onnx())  # the "download" is another file
    monkeypatch.setattr(N, "NANODET_URL_BASE", mirror.as_uri() + "/")
    monkeypatch.setenv("MASSVIZ_CACHE_DIR", str(tmp_path / "cache"))
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    code, err, out = _estimate(tmp_path, capsys, "--weights", str(weights))
    assert code == 2 and len(err) == 1, err
    assert N.NANODET_NAME in err[0] and "sha256" in err[0] and N.NANODET_SHA256 in err[0]
    assert not out.exists()
    assert not any((tmp_path / "cache").rglob("*.onnx")) and not any((tmp_path / "cache").rglob("*tmp*"))


def test_settings_key_the_model_by_content(shared_dir, tmp_path):
    model = shared_dir / "detectors" / "nanodet" / N.NANODET_NAME
    a = N.NanoDetDetector(weights=model).settings()
    copy = tmp_path / "copy.onnx"
    copy.write_bytes(model.read_bytes())
    assert N.NanoDetDetector(weights=copy, threshold=0.7).settings() == a  # same content, any name, any threshold
    assert N.NanoDetDetector(weights=model, nms_iou=0.5).settings() != a
    copy.write_bytes(relu_onnx())
    with pytest.raises(WeightsError, match="not OpenCV Zoo's NanoDet"):  # never a cache key for a file it cannot run
        N.NanoDetDetector(weights=copy).settings()


def test_reduced_precision_is_refused_with_one_line(tmp_path, capsys, shared_dir):
    model = shared_dir / "detectors" / "nanodet" / N.NANODET_NAME
    weights = shared_dir / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    code, err, out = _estimate(tmp_path, capsys, "--detector-weights", str(model), "--weights", str(weights),
                               "--precision", "bf16")
    assert code == 2 and len(err) == 1 and "nanodet detector runs in fp32 only" in err[0] and not out.exists()
