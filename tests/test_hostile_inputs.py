"""Hostile inputs: every file a dataset brings and every option value, mutated from the bundled samples.

Each case writes one hostile input into a fresh folder (a 3-frame copy of ``data_samples/cup_handover``, a CCM-layout
copy of it, a replay JSON, a checkpoint, CSVs, ...), runs the command in-process (``massviz.cli.main``) and asserts:
exit code 2, exactly one line on stderr, that line is ``massviz CMD: error: <the file or option>: ...`` and says what
is wrong, no internal error or traceback, the named outputs do not exist and nothing at all was written in the case's
folder (the cache may hold file digests, never a trace). Calibration pickles that try to run code leave a canary
file behind if they ran. A few cases run as real subprocesses, and a few hostile inputs that must be *accepted*
(ids that need sanitising, a partial video with --allow-partial, stale or corrupt cache entries) check what they
write instead.
"""
from __future__ import annotations

import io
import json
import os
import pickle
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from fakes import (
    ANN_HEADER,
    ANN_ROWS,
    PRED_HEADER,
    PRED_ROWS,
    SAMPLE,
    Base,
    Evil,
    calib,
    copy_sample,
    csv_text,
    faststart,
    make_ccm,
    png_header_only,
    run_cli,
    snapshot,
    visible_lines,
)
from support import run_massviz

ROOT = Path(__file__).resolve().parents[1]
W, H = 480, 270



# ============================================================================================================= cases
@dataclass
class Case:
    name: str
    build: Callable  # (work dir, Base) -> (argv, culprit, pattern[, outputs])
    code: int = 2


CASES: list[Case] = []


def case(name: str, code: int = 2):
    def register(fn):
        CASES.append(Case(name, fn, code))
        return fn
    return register


def estimate(work: Path, b: Base, rec: Path, *extra, replay: Path | None = None, weights: Path | None = None):
    out = work / "preds.csv"
    argv = ["estimate", rec, "--out", out, "--detector", "replay", "--replay", replay or b.replay,
            "--weights", weights or b.weights, "--cache", work / "cache", "--quiet", *extra]
    return argv, out


def edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


# --- intrinsics.json -------------------------------------------------------------------------------------------
INTRINSICS = {
    "fx_nan": ("fx", float("nan"), "finite"), "fx_inf": ("fx", float("inf"), "finite"),
    "fx_zero": ("fx", 0, "> 0"), "fx_negative": ("fx", -346.4, "> 0"), "fy_text": ("fy", "346", "number"),
    "fy_bool": ("fy", True, "number"), "cx_nan": ("cx", float("nan"), "finite"),
    "cx_outside": ("cx", 1e9, "<="), "cy_negative": ("cy", -5.0, ">="), "width_fraction": ("width", 480.5, "integer"),
    "width_zero": ("width", 0, ">"), "height_huge": ("height", 10**30, "<="), "height_null": ("height", None, "number"),
}
for _name, (_key, _value, _what) in INTRINSICS.items():
    def _build(work, b, key=_key, value=_value, what=_what):
        rec = copy_sample(work / "rec")
        edit_json(rec / "intrinsics.json", lambda d: d.__setitem__(key, value))
        argv, out = estimate(work, b, rec)
        return argv, rec / "intrinsics.json", rf"{key}.*{what}|{what}.*{key}", [out]
    case(f"intrinsics-{_name}")(_build)


@case("intrinsics-not-object")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "intrinsics.json").write_text("[346.4, 346.3]")
    argv, out = estimate(work, b, rec)
    return argv, rec / "intrinsics.json", "JSON object", [out]


@case("intrinsics-binary")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "intrinsics.json").write_bytes(b"\xff\xfe\x00garbage")
    argv, out = estimate(work, b, rec)
    return argv, rec / "intrinsics.json", "JSON", [out]


# --- meta.json --------------------------------------------------------------------------------------------------
META = {
    "fps_nan": (lambda d: d.update(fps=float("nan")), "fps.*finite"),
    "fps_zero": (lambda d: d.update(fps=0), "fps.*> 0"),
    "fps_negative": (lambda d: d.update(fps=-30), "fps.*> 0"),
    "fps_inf": (lambda d: d.update(fps=float("inf")), "fps.*finite"),
    "fps_huge": (lambda d: d.update(fps=1e9), "fps.*<="),
    "id_newline": (lambda d: d.update(id="cup\nmassviz estimate: wrote nothing"), "id.*control"),
    "id_escape": (lambda d: d.update(id="\x1b[2Jcup"), "id.*control"),
    "id_bidi": (lambda d: d.update(id="cup\u202egnp.exe"), "id.*control"),
    "id_object": (lambda d: d.update(id={"a": 1}), "id.*string"),
    "id_empty": (lambda d: d.update(id=""), "id.*empty"),
    "id_long": (lambda d: d.update(id="x" * 5000), "id.*long"),
    "config_id_control": (lambda d: d.update(config_id="7\r8"), "config_id.*control"),
    "config_id_float": (lambda d: d.update(config_id=1e30), "config_id.*string"),
    "mass_nan": (lambda d: d["container"].update(mass_g=float("nan")), "mass_g.*finite"),
    "mass_inf": (lambda d: d["container"].update(mass_g=float("inf")), "mass_g.*finite"),
    "mass_negative": (lambda d: d["container"].update(mass_g=-9.0), "mass_g.*> 0"),
    "height_inf": (lambda d: d["container"].update(height_mm=float("inf")), "height_mm.*finite"),
    "container_list": (lambda d: d.update(container=[1, 2]), "container.*object"),
    "masks_escape": (lambda d: d.update(instance_masks="../../{frame:06d}.png"), "instance_masks.*outside"),
    "masks_absolute": (lambda d: d.update(instance_masks="/etc/{frame:06d}.png"), "instance_masks.*absolute"),
    "masks_attribute": (lambda d: d.update(instance_masks="gt/{frame.__class__}.png"), "instance_masks"),
    "masks_width": (lambda d: d.update(instance_masks="gt/{frame:999999999}.png"), "instance_masks"),
    "masks_positional": (lambda d: d.update(instance_masks="gt/{0}.png"), "instance_masks"),
    "instance_id_huge": (lambda d: d["instances"].update({"1e400": "x"}), "instances"),
}
for _name, (_edit, _what) in META.items():
    def _build(work, b, edit=_edit, what=_what):
        rec = copy_sample(work / "rec")
        edit_json(rec / "meta.json", edit)
        argv, out = estimate(work, b, rec)
        return argv, rec / "meta.json", what, [out]
    case(f"meta-{_name}")(_build)


@case("meta-not-object")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "meta.json").write_text('"cup"')
    argv, out = estimate(work, b, rec)
    return argv, rec / "meta.json", "JSON object", [out]


@case("meta-duplicate-config-id")
def _(work, b):
    for name in ("a", "b"):
        edit_json(copy_sample(work / "ds" / name) / "meta.json", lambda d, name=name: d.update(config_id=7, id=name))
    argv, out = estimate(work, b, work / "ds")
    return argv, work / "ds" / "b", "configuration id 7 is also the id of", [out]


# --- images and videos ------------------------------------------------------------------------------------------
@case("depth-header-bomb")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "depth" / "000000.png").write_bytes(png_header_only(100_000, 100_000))
    argv, out = estimate(work, b, rec)
    return argv, rec / "depth" / "000000.png", "100000x100000.*not decoded", [out]


@case("rgb-header-bomb")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "rgb" / "000000.png").write_bytes(png_header_only(60_000, 60_000))
    argv, out = estimate(work, b, rec)
    return argv, rec / "rgb" / "000000.png", "60000x60000.*not decoded", [out]


@case("depth-header-bomb-mid-stream")
def _(work, b):
    rec = copy_sample(work / "rec")
    (rec / "depth" / "000002.png").write_bytes(png_header_only(20_000, 20_000))
    argv, out = estimate(work, b, rec)
    return argv, rec / "depth" / "000002.png", "20000x20000", [out]


@case("depth-truncated-mid-stream")
def _(work, b):
    rec = copy_sample(work / "rec")
    data = (rec / "depth" / "000002.png").read_bytes()
    (rec / "depth" / "000002.png").write_bytes(data[:len(data) // 3])
    argv, out = estimate(work, b, rec)
    return argv, rec / "depth" / "000002.png", "cannot read depth", [out]


@case("rgb-size-mid-stream")
def _(work, b):
    rec = copy_sample(work / "rec")
    cv2.imwrite(str(rec / "rgb" / "000002.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    argv, out = estimate(work, b, rec)
    return argv, rec / "rgb" / "000002.png", "declares 240x135 pixels but the recording.s frames are 480x270", [out]


def truncated_video(work: Path) -> Path:
    rec = copy_sample(work / "rec", n=12, video=True)
    data = faststart((rec / "rgb.mp4").read_bytes())
    (rec / "rgb.mp4").write_bytes(data[:len(data) // 2])
    return rec


@case("video-cut-in-half")
def _(work, b):
    rec = truncated_video(work)
    argv, out = estimate(work, b, rec)
    return argv, rec / "rgb.mp4", r"only \d+ of the 12 frames", [out]


@case("video-garbage")
def _(work, b):
    rec = copy_sample(work / "rec", video=True)
    (rec / "rgb.mp4").write_bytes(np.random.default_rng(1).integers(0, 256, 5000, np.uint8).tobytes())
    argv, out = estimate(work, b, rec)
    return argv, rec / "rgb.mp4", "cannot decode video", [out]


@case("video-index-at-end-cut")
def _(work, b):
    rec = copy_sample(work / "rec", video=True)
    data = (rec / "rgb.mp4").read_bytes()
    (rec / "rgb.mp4").write_bytes(data[:len(data) // 2])
    argv, out = estimate(work, b, rec)
    return argv, rec / "rgb.mp4", "cannot decode video", [out]


# --- CCM calibration pickles ------------------------------------------------------------------------------------
def _reduce_pickle(module: str, name: str, arg: str, protocol: int = 0) -> bytes:
    """A pickle calling ``module.name(arg)``, written opcode by opcode (no live object needed)."""
    if protocol == 0:
        return f"c{module}\n{name}\n(S{arg!r}\ntR.".encode()
    return (b"\x80\x04" + pickle.dumps(module, 4)[2:-1] + pickle.dumps(name, 4)[2:-1] + b"\x93"
            + pickle.dumps(arg, 4)[2:-1] + b"\x85R.")


def evil_calib(work: Path, how: str, protocol: int) -> bytes:
    canary = work / "CANARY"
    structure = calib()
    structure[0]["rgb"] = Evil(canary, how)
    return pickle.dumps(structure, protocol=protocol)


PICKLES = {
    # code execution: each would create work/CANARY if anything in the file ran
    "os_system_p0": (lambda w: evil_calib(w, "os", 0), "refused.*system"),
    "os_system_p2": (lambda w: evil_calib(w, "os", 2), "refused.*system"),
    "os_system_p5": (lambda w: evil_calib(w, "os", 5), "refused.*system"),
    "subprocess_p4": (lambda w: evil_calib(w, "subprocess", 4), "refused.*subprocess"),
    "eval_p3": (lambda w: evil_calib(w, "eval", 3), "refused.*eval"),
    "stack_global_system": (lambda w: _reduce_pickle("os", "system", f"touch {w / 'CANARY'}", 4), "refused"),
    "builtins_exec": (lambda w: _reduce_pickle("builtins", "exec", f"open({str(w / 'CANARY')!r},'w')"), "refused"),
    "class_instance": (lambda w: pickle.dumps([{"rgb": __import__("collections").OrderedDict()}], 2),
                       "refused.*OrderedDict"),
    "ndarray_called": (lambda w: b"cnumpy\nndarray\n(I100000000\ntR.", "not a CCM calibration pickle"),
    "huge_array": (lambda w: b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n(I1000000000\ntS'b'\ntR.",
                   "not a CCM calibration pickle"),
    "object_array": (lambda w: pickle.dumps([{"rgb": np.array([None, 1], dtype=object)}], 2), "only numeric"),
    "persistent_id": (lambda w: b"P1\n.", "persistent"),
    # malformed but harmless
    "fx_zero": (lambda w: pickle.dumps(calib(fx=0.0), 0), "fx.*> 0"),
    "fx_nan": (lambda w: pickle.dumps(calib(fx=float("nan")), 0), "fx.*finite"),
    "cy_inf": (lambda w: pickle.dumps(calib(cy=float("inf")), 0), "cy.*finite"),
    "matrix_2x2": (lambda w: pickle.dumps([{"rgb": np.eye(2)}], 0), "shape"),
    "not_a_list": (lambda w: pickle.dumps({"rgb": np.eye(3)}, 0), "not a CCM calibration pickle"),
    "truncated": (lambda w: pickle.dumps(calib(), 0)[:300], "not a CCM calibration pickle"),
    "empty": (lambda w: b"", "not a CCM calibration pickle"),
    "too_big": (lambda w: pickle.dumps([calib(), b"x" * (2 << 20)], 4), "bytes"),
}
for _name, (_payload, _what) in PICKLES.items():
    def _build(work, b, payload=_payload, what=_what):
        video = make_ccm(work / "ccm", payload(work))
        argv, out = estimate(work, b, video)
        return argv, video.parents[1] / "calib" / "000000.pickle", what, [out, work / "CANARY"]
    case(f"calib-{_name}")(_build)


# --- replay detections (JSON and trace .npz) --------------------------------------------------------------------
def replay_case(edit, what: str, mask: str | None = None):
    def build(work, b):
        rec = copy_sample(work / "rec")
        det = {"frame": 1, "box": list(b.box), "score": 0.9, "class": "cup"}
        doc = {"detections": [det]}
        (work / "outside.png").write_bytes(cv2.imencode(".png", np.full((H, W), 255, np.uint8))[1].tobytes())
        replay_dir = work / "replay"
        replay_dir.mkdir()
        edit(doc, det, work, replay_dir)
        path = replay_dir / "dets.json"
        path.write_text(json.dumps(doc))
        argv, out = estimate(work, b, rec, replay=path)
        return argv, path, what, [out]
    return build


REPLAYS = {
    "mask_parent": (lambda d, det, w, r: det.update(mask="../outside.png"), "mask.*outside"),
    "mask_absolute": (lambda d, det, w, r: det.update(mask=str(w / "outside.png")), "mask.*absolute"),
    "mask_dotdot_inside": (lambda d, det, w, r: det.update(mask="sub/../../outside.png"), "mask.*outside"),
    "mask_number": (lambda d, det, w, r: det.update(mask=12), "mask.*relative file path"),
    "box_inf": (lambda d, det, w, r: det.update(box=[0, 0, float("inf"), 10]), "box.*finite"),
    "box_nan": (lambda d, det, w, r: det.update(box=[0, 0, float("nan"), 10]), "box.*finite"),
    "box_1e30": (lambda d, det, w, r: det.update(box=[0, 0, 1e30, 1e30]), "box.*<="),
    "box_huge_int": (lambda d, det, w, r: det.update(box=[0, 0, 2**31 + 5, 100]), "box.*<="),
    "box_gigapixel": (lambda d, det, w, r: det.update(box=[0, 0, 100_000, 100_000]), "outside the 480x270 frame"),
    "box_negative": (lambda d, det, w, r: det.update(box=[-20, 5, 40, 60]), "box.*>= 0"),
    "box_three": (lambda d, det, w, r: det.update(box=[1, 2, 3]), "box"),
    "box_text": (lambda d, det, w, r: det.update(box=["a", 0, 10, 10]), "box"),
    "box_empty": (lambda d, det, w, r: det.update(box=[10, 10, 10, 20]), "empty box"),
    "frame_1e30": (lambda d, det, w, r: det.update(frame=1e30), "frame.*<="),
    "frame_negative": (lambda d, det, w, r: det.update(frame=-1), "frame.*>= 0"),
    "frame_fraction": (lambda d, det, w, r: det.update(frame=1.5), "frame.*integer"),
    "score_nan": (lambda d, det, w, r: det.update(score=float("nan")), "score.*finite"),
    "score_above_one": (lambda d, det, w, r: det.update(score=7.0), "score.*<= 1"),
    "class_bool": (lambda d, det, w, r: det.update({"class": True}), "class"),
    "class_huge": (lambda d, det, w, r: det.update({"class": 10**20}), "class"),
    "detections_not_list": (lambda d, det, w, r: d.update(detections={"0": det}), "detections"),
}
for _name, (_edit, _what) in REPLAYS.items():
    case(f"replay-{_name}")(replay_case(_edit, _what))


@case("replay-mask-header-bomb")
def _(work, b):
    argv, path, _, outputs = replay_case(lambda d, det, w, r: ((r / "m.png").write_bytes(png_header_only(90_000,
                                                                                                        90_000)),
                                                               det.update(mask="m.png")), "")(work, b)
    return argv, path.parent / "m.png", "90000x90000.*not decoded", outputs


def npz_case(edit, what: str):
    """A trace .npz saved by a real run, one array or the header changed."""
    def build(work, b):
        rec = copy_sample(work / "rec")
        with np.load(b.trace_npz) as z:
            arrays = {k: z[k] for k in z.files}
        header = json.loads(arrays["header"].tobytes())
        edit(arrays, header)
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
        path = work / "trace.npz"
        np.savez(path, **arrays)
        argv, out = estimate(work, b, rec, replay=path)
        return argv, path, what, [out]
    return build


NPZS = {
    "mask_shape_huge": (lambda a, h: a.__setitem__("mask_shapes", np.full_like(a["mask_shapes"], 2**30)), "mask"),
    "mask_bits_short": (lambda a, h: a.__setitem__("mask_bits", a["mask_bits"][:1]), "mask"),
    "box_outside_int": (lambda a, h: a.__setitem__("det_xyxy", a["det_xyxy"].astype(np.int64) * 0 + 2**40), "xyxy"),
    "frame_negative": (lambda a, h: a.__setitem__("det_frame", a["det_frame"] * 0 - 3), "frame"),
    "score_nan": (lambda a, h: a.__setitem__("det_score", a["det_score"] * np.nan), "score"),
    "patch_not_png": (lambda a, h: a.__setitem__("patch_bytes", np.zeros_like(a["patch_bytes"])), "patch"),
    "patch_sizes_lie": (lambda a, h: a.__setitem__("patch_sizes", a["patch_sizes"] * 1000), "patch"),
    "selection_out_of_range": (lambda a, h: a.__setitem__("selection", a["selection"] + 10**6), "selection"),
    "header_k_nan": (lambda a, h: h.update(k=float("nan")), "k"),
    "header_threshold_text": (lambda a, h: h.update(threshold="high"), "threshold"),
    "object_array": (lambda a, h: a.__setitem__("det_d", np.array([None] * len(a["det_d"]), dtype=object)), "trace"),
}
for _name, (_edit, _what) in NPZS.items():
    case(f"replay-npz-{_name}")(npz_case(_edit, _what))


@case("replay-npz-array-header-bomb")
def _(work, b):
    """An .npz member whose .npy header declares 10^12 float64 values (8 TB) in a few bytes of data."""
    rec = copy_sample(work / "rec")
    import zipfile

    path = work / "trace.npz"
    shutil.copy(b.trace_npz, path)
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**12,)}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    with zipfile.ZipFile(path, "a") as z:
        z.writestr("det_d.npy", buf.getvalue() + b"\0" * 64)
    argv, out = estimate(work, b, rec, replay=path)
    return argv, path, "trace", [out]


@case("replay-npz-garbage")
def _(work, b):
    rec = copy_sample(work / "rec")
    path = work / "trace.npz"
    path.write_bytes(b"PK\x03\x04 not really a zip")
    argv, out = estimate(work, b, rec, replay=path)
    return argv, path, "not a massviz trace", [out]


# --- checkpoints and ranges -------------------------------------------------------------------------------------
def checkpoint_case(make, what: str, culprit: str = "weights"):
    def build(work, b):
        import torch

        rec = copy_sample(work / "rec")
        path = work / "ckpt.torch"
        payload = torch.load(b.weights, weights_only=True)
        result = make(payload, path, work)
        if result is not None:
            torch.save(result, path)
        argv, out = estimate(work, b, rec, weights=path)
        named = path if culprit == "weights" else path.with_name(path.name + ".ranges.json")
        return argv, named, what, [out, work / "CANARY"]
    return build


def _write(path: Path, data: bytes) -> None:
    path.write_bytes(data)  # the file itself is the case: nothing for torch.save to write


def _nan_weights(p, path, work):
    p["state_dict"]["linear3.weight"][0, 0] = float("nan")
    return p


def _inf_bn(p, path, work):
    p["state_dict"]["bn1.running_var"][3] = float("inf")
    return p


def _sidecar(text):
    def make(p, path, work):
        del p["ranges"]
        p["state_dict"]["linear3.bias"] += 1  # not the published file: its ranges come from the sidecar
        path.with_name(path.name + ".ranges.json").write_text(text)
        return p
    return make


RANGES = {"minAverageDistance": 0, "maxAverageDistance": 1500, "minRatioWidth": 0, "maxRatioWidth": 1,
          "minRatioHeight": 0, "maxRatioHeight": 1, "minMass": 1, "maxMass": 200}
CHECKPOINTS = {
    "empty_file": (lambda p, path, w: _write(path, b""), "cannot read checkpoint"),
    "garbage": (lambda p, path, w: _write(path, os.urandom(3000)), "cannot read checkpoint"),
    "nan_weights": (_nan_weights, "linear3.weight.*(NaN|finite)"),
    "inf_running_var": (_inf_bn, "bn1.running_var.*(NaN|finite|inf)"),
    "wrong_shape": (lambda p, path, w: p["state_dict"].update({"linear3.weight": p["state_dict"]["linear3.weight"][:, :4]})
                    or p, "wrong shape"),
    "code_execution": (lambda p, path, w: _write(path, pickle.dumps(Evil(w / "CANARY"))), "cannot read checkpoint"),
    "ranges_nan": (lambda p, path, w: p["ranges"].update(minMass=float("nan")) or p, "finite"),
    "ranges_inverted": (lambda p, path, w: p["ranges"].update(minMass=500.0) or p, "max must exceed"),
    "ranges_overflow": (lambda p, path, w: p["ranges"].update(minMass=-1.5e308, maxMass=1.5e308) or p, "finite"),
    "ranges_text": (lambda p, path, w: p["ranges"].update(maxMass="200") or p, "finite number"),
}
for _name, (_make, _what) in CHECKPOINTS.items():
    case(f"checkpoint-{_name}")(checkpoint_case(_make, _what))
case("ranges-sidecar-invalid-json")(checkpoint_case(_sidecar("{not json"), "cannot read ranges", culprit="sidecar"))
case("ranges-sidecar-infinity")(checkpoint_case(_sidecar(json.dumps({**RANGES, "maxMass": float("inf")})), "finite",
                                                culprit="sidecar"))
case("ranges-sidecar-keys")(checkpoint_case(_sidecar(json.dumps({"minMass": 1})), "keys", culprit="sidecar"))


@case("checkpoint-is-directory")
def _(work, b):
    rec = copy_sample(work / "rec")
    (work / "ckpt.torch").mkdir()
    argv, out = estimate(work, b, rec, weights=work / "ckpt.torch")
    return argv, work / "ckpt.torch", "not found|directory", [out]



def score_case(which: str, column: str, value: str, what: str):
    def build(work, b):
        ann, pred = work / "ann.csv", work / "pred.csv"
        ann.write_text(csv_text(ANN_HEADER, ANN_ROWS, *((1, column, value) if which == "ann" else ())))
        pred.write_text(csv_text(PRED_HEADER, PRED_ROWS, *((1, column, value) if which == "pred" else ())))
        out = work / "score.json"
        return ["score", pred, "--annotations", ann, "--json", out], ann if which == "ann" else pred, what, [out]
    return build


CSVS = {
    "ann-id-1e30": ("ann", "id", "1e30", "row 2.*'id'.*<="),
    "ann-id-negative": ("ann", "id", "-4", "row 2.*'id'.*>= 0"),
    "ann-id-nan": ("ann", "id", "nan", "row 2.*'id'.*integer"),
    "ann-id-inf": ("ann", "id", "inf", "row 2.*'id'.*integer"),
    "ann-id-control": ("ann", "id", "1\x1b[2J", "row 2.*'id'"),
    "ann-container-1e30": ("ann", "container id", "1e30", "row 2.*'container id'.*<="),
    "ann-mass-inf": ("ann", "container mass", "inf", "row 2.*'container mass'.*finite"),
    "ann-mass-nan": ("ann", "container mass", "nan", "row 2.*'container mass'.*finite"),
    "ann-mass-zero": ("ann", "container mass", "0", "row 2.*'container mass'.*> 0"),
    "ann-width-inf": ("ann", "width at the top", "inf", "row 2.*'width at the top'.*finite"),
    "ann-height-text": ("ann", "height", "tall", "row 2.*'height'.*number"),
    "pred-id-1e30": ("pred", "Configuration ID", "1e30", "row 2.*'Configuration ID'.*<="),
    "pred-id-negative": ("pred", "Configuration ID", "-2", "row 2.*'Configuration ID'.*>= 0"),
    "pred-id-text": ("pred", "Configuration ID", "12abc", "row 2.*'Configuration ID'.*integer"),
    "pred-mass-inf": ("pred", "Container mass", "inf", "row 2.*'Container mass'.*finite"),
    "pred-mass-nan": ("pred", "Container mass", "nan", "row 2.*'Container mass'.*finite"),
    "pred-mass-huge": ("pred", "Container mass", "1e400", "row 2.*'Container mass'.*finite"),
}
for _name, (_which, _column, _value, _what) in CSVS.items():
    case(f"csv-{_name}")(score_case(_which, _column, _value, _what))


@case("csv-ann-not-utf8")
def _(work, b):
    ann, pred = work / "ann.csv", work / "pred.csv"
    ann.write_bytes(b"\xff\xfe\x00i\x00d\x00")
    pred.write_text(csv_text(PRED_HEADER, PRED_ROWS))
    out = work / "M4.csv"
    return ["baseline", "random", "--annotations", ann, "--out", out], ann, "not UTF-8", [out]


# --- exclusions -------------------------------------------------------------------------------------------------
def exclusion_case(entry_edit, what: str, doc_edit=None):
    def build(work, b):
        rec = copy_sample(work / "rec")
        entry = {"recording": "cup_handover", "frame": 1, "box": list(b.box), "note": "pitcher"}
        doc = {"format": "massviz.exclusions/1", "exclusions": [entry]}
        entry_edit(entry)
        if doc_edit:
            doc_edit(doc)
        path = work / "exclude.json"
        path.write_text(json.dumps(doc))
        argv, out = estimate(work, b, rec, "--exclude", path)
        return argv, path, what, [out]
    return build


EXCLUSIONS = {
    "frame_huge": (lambda e: e.update(frame=10**30), "frame.*<="),
    "frame_float": (lambda e: e.update(frame=1.0), "frame.*integer"),
    "box_huge": (lambda e: e.update(box=[0, 0, 10**30, 10]), "box"),
    "box_nan": (lambda e: e.update(box=[0, 0, float("nan"), 10]), "box"),
    "recording_control": (lambda e: e.update(recording="cup\x1b]0;pwned\x07"), "recording.*control"),
    "recording_number": (lambda e: e.update(recording=5), "recording"),
    "note_object": (lambda e: e.update(note={"x": 1}), "note"),
    "note_control": (lambda e: e.update(note="a\x1b[2Jb"), "note.*control"),
}
for _name, (_edit, _what) in EXCLUSIONS.items():
    case(f"exclude-{_name}")(exclusion_case(_edit, _what))
case("exclude-not-list")(exclusion_case(lambda e: None, "exclusions.*list",
                                        doc_edit=lambda d: d.update(exclusions={"a": 1})))


# --- patch sets (train) -----------------------------------------------------------------------------------------
def index_case(edit, what: str):
    def build(work, b):
        patches = work / "patches"
        (patches / "images").mkdir(parents=True)
        rows = []
        for r in range(4):
            name = f"images/rec{r}_0.png"
            cv2.imwrite(str(patches / name), np.full((20, 16, 3), 40 * r, np.uint8))
            rows.append({"file": name, "recording": f"rec{r}", "a": 0.1, "b": 0.2, "d": 900.0 + r,
                         "mass_g": 10.0 + r, "container_id": r + 1})
        edit(rows, work)
        import pandas as pd

        pd.DataFrame(rows).to_csv(patches / "index.csv", index=False)
        out = work / "run"
        return ["train", patches, "--out", out, "--epochs", "1", "--quiet"], patches / "index.csv", what, [out]
    return build


INDEXES = {
    "file_parent": (lambda rows, w: rows[1].update(file="../../outside.png"), "file.*outside"),
    "file_absolute": (lambda rows, w: rows[1].update(file=str(SAMPLE / "rgb" / "000000.png")), "file.*absolute"),
    "a_nan": (lambda rows, w: rows[2].update(a=float("nan")), "'a'.*finite"),
    "mass_inf": (lambda rows, w: rows[2].update(mass_g=float("inf")), "'mass_g'.*finite"),
    "container_1e30": (lambda rows, w: rows[2].update(container_id=1e30), "container_id"),
    "recording_control": (lambda rows, w: rows[2].update(recording="r\x1b[1m"), "recording.*control"),
}
for _name, (_edit, _what) in INDEXES.items():
    case(f"index-{_name}")(index_case(_edit, _what))


# --- output paths -----------------------------------------------------------------------------------------------
def read_only_dir(work: Path) -> Path:
    """A folder nobody may write in: chmod 555 for a normal user; for root (which ignores modes) /sys."""
    if os.geteuid() != 0:
        d = work / "ro"
        d.mkdir()
        d.chmod(0o555)
        return d
    if os.access("/sys", os.W_OK) and Path("/sys").is_dir():
        try:
            Path("/sys/.massviz-probe").touch()
        except OSError:
            return Path("/sys")
        pytest.skip("no read-only folder available")
    return Path("/sys")


def pipeline(work: Path, b: Base, command: str, *extra, rec: Path | None = None):
    rec = rec or copy_sample(work / "rec")
    return [command, rec, *extra, "--detector", "replay", "--replay", b.replay, "--weights", b.weights,
            "--cache", work / "cache", "--quiet"]


def _file(path: Path) -> Path:
    path.write_text("not a folder\n")
    return path


OUTPUTS = {
    # name: (argv builder (work, b) -> (argv, culprit path), pattern)
    "estimate-out-is-dir": (lambda w, b: ((w / "out").mkdir(), (pipeline(w, b, "estimate", "--out", w / "out"),
                                                              w / "out"))[1], "is a directory"),
    "estimate-out-parent-missing": (lambda w, b: (pipeline(w, b, "estimate", "--out", w / "no" / "p.csv"),
                                                  w / "no" / "p.csv"), "folder .* does not exist"),
    "estimate-out-parent-is-file": (lambda w, b: (pipeline(w, b, "estimate", "--out", _file(w / "f") / "p.csv"),
                                                  w / "f" / "p.csv"), "not a folder"),
    "estimate-out-read-only": (lambda w, b: (pipeline(w, b, "estimate", "--out", read_only_dir(w) / "p.csv"),
                                             read_only_dir(w) / "p.csv"), "cannot write"),
    "estimate-cache-is-file": (lambda w, b: ([*pipeline(w, b, "estimate", "--out", w / "p.csv"), "--cache",
                                              _file(w / "cachefile")], w / "cachefile"), "not a folder"),
    "estimate-cache-read-only": (lambda w, b: ([*pipeline(w, b, "estimate", "--out", w / "p.csv"), "--cache",
                                                read_only_dir(w) / "cache"], read_only_dir(w) / "cache"),
                                 "cannot write"),
    "log-rrd-is-dir": (lambda w, b: ((w / "o.rrd").mkdir(), (pipeline(w, b, "log", "--rrd", w / "o.rrd"),
                                                            w / "o.rrd"))[1], "is a directory"),
    "log-rrd-parent-missing": (lambda w, b: (pipeline(w, b, "log", "--rrd", w / "no" / "o.rrd"),
                                             w / "no" / "o.rrd"), "does not exist"),
    "log-ply-is-file": (lambda w, b: (pipeline(w, b, "log", "--rrd", w / "o.rrd", "--ply", _file(w / "ply")),
                                      w / "ply"), "not a folder"),
    "log-ply-read-only": (lambda w, b: (pipeline(w, b, "log", "--rrd", w / "o.rrd", "--ply",
                                                 read_only_dir(w) / "ply"), read_only_dir(w) / "ply"), "cannot write"),
    "cloud-out-is-file": (lambda w, b: (pipeline(w, b, "cloud", "--out", _file(w / "c")), w / "c"), "not a folder"),
    "cloud-out-under-file": (lambda w, b: (pipeline(w, b, "cloud", "--out", _file(w / "c") / "sub"), w / "c" / "sub"),
                             "not a folder"),
    "render-out-is-dir": (lambda w, b: ((w / "r.png").mkdir(), (pipeline(w, b, "render", "--out", w / "r.png"),
                                                               w / "r.png"))[1], "is a directory"),
    "render-out-parent-missing": (lambda w, b: (pipeline(w, b, "render", "--out", w / "no" / "r.png"),
                                                w / "no" / "r.png"), "does not exist"),
    "sweep-csv-is-dir": (lambda w, b: ((w / "s.csv").mkdir(), ([*pipeline(w, b, "sweep"), "--csv", w / "s.csv"],
                                                              w / "s.csv"))[1], "is a directory"),
    "sweep-plot-parent-missing": (lambda w, b: ([*pipeline(w, b, "sweep"), "--plot", w / "no" / "h.png"],
                                                w / "no" / "h.png"), "does not exist"),
    "extract-out-parent-is-file": (lambda w, b: (pipeline(w, b, "extract", "--out", _file(w / "f") / "patches"),
                                                 w / "f" / "patches"), "not a folder"),
    "train-out-is-file": (lambda w, b: (["train", w, "--out", _file(w / "run"), "--quiet"], w / "run"),
                          "not a folder"),
    "samples-out-is-file": (lambda w, b: (["samples", "--out", _file(w / "samples")], w / "samples"), "not a folder"),
}


def _scored(work: Path, *extra):
    ann, pred = work / "ann.csv", work / "pred.csv"
    ann.write_text(csv_text(ANN_HEADER, ANN_ROWS))
    pred.write_text(csv_text(PRED_HEADER, PRED_ROWS))
    return ["score", pred, "--annotations", ann, *extra]


OUTPUTS.update({
    "score-json-is-dir": (lambda w, b: ((w / "s.json").mkdir(), (_scored(w, "--json", w / "s.json"),
                                                                w / "s.json"))[1], "is a directory"),
    "score-plot-parent-is-file": (lambda w, b: (_scored(w, "--plot", _file(w / "f") / "p.png"), w / "f" / "p.png"),
                                  "not a folder"),
    "baseline-out-is-dir": (lambda w, b: ((w / "m4.csv").mkdir(), ([*_scored(w)[:0], "baseline", "random",
                                                                   "--annotations", _scored(w)[3], "--out",
                                                                   w / "m4.csv"], w / "m4.csv"))[1],
                            "is a directory"),
})
for _name, (_make, _what) in OUTPUTS.items():
    def _build(work, b, make=_make, what=_what):
        argv, culprit = make(work, b)
        return argv, culprit, what, []
    case(f"output-{_name}")(_build)


# --- option values ----------------------------------------------------------------------------------------------
OPTIONS = {
    "render-yaw-nan": ("render", ["--out", "r.png", "--yaw", "nan"], "--yaw", "finite"),
    "render-yaw-inf": ("render", ["--out", "r.png", "--yaw", "inf"], "--yaw", "finite"),
    "render-pitch-90": ("render", ["--out", "r.png", "--pitch", "90"], "--pitch", "<"),
    "render-pitch-nan": ("render", ["--out", "r.png", "--pitch", "nan"], "--pitch", "finite"),
    "render-frame-negative": ("render", ["--out", "r.png", "--frame", "-1"], "--frame", ">= 0"),
    "render-frame-past-end": ("render", ["--out", "r.png", "--frame", "999"], "--frame", "frames"),
    "render-size-huge": ("render", ["--out", "r.png", "--size", "100000x100000"], "--size", "between"),
    "estimate-threshold-nan": ("estimate", ["--out", "p.csv", "--threshold", "nan"], "--threshold", r"\[0, 1\)"),
    "estimate-threshold-inf": ("estimate", ["--out", "p.csv", "--threshold", "inf"], "--threshold", r"\[0, 1\)"),
    "estimate-k-zero": ("estimate", ["--out", "p.csv", "--k", "0"], "--k", ">= 1"),
    "estimate-stride-zero": ("estimate", ["--out", "p.csv", "--stride", "0"], "--stride", ">= 1"),
    "sweep-step-tiny": ("sweep", ["--threshold", "0:0.9:1e-9"], "--threshold", "values"),
    "sweep-stop-inf": ("sweep", ["--threshold", "0:inf:0.1"], "--threshold", "finite"),
    "sweep-list-nan": ("sweep", ["--threshold", "0.4,nan"], "--threshold", "finite"),
    "sweep-value-nan": ("sweep", ["--threshold", "nan"], "--threshold", "finite"),
    "sweep-k-huge": ("sweep", ["--k", "1:100000000"], "--k", "values"),
    "sweep-k-zero": ("sweep", ["--k", "0:5"], "--k", ">= 1"),
}
for _name, (_command, _extra, _option, _what) in OPTIONS.items():
    def _build(work, b, command=_command, extra=_extra, option=_option, what=_what):
        extra = [work / e if e.endswith((".png", ".csv")) else e for e in extra]
        return pipeline(work, b, command, *extra), option, what, [work / "r.png", work / "p.csv"]
    case(f"option-{_name}")(_build)

TRAIN_OPTIONS = {"lr-nan": ("--lr", "nan", "finite"), "lr-zero": ("--lr", "0", "> 0"),
                 "lr-inf": ("--lr", "inf", "finite"), "epochs-zero": ("--epochs", "0", ">= 1"),
                 "batch-one": ("--batch-size", "1", ">= 2"), "augment-zero": ("--augment", "0", ">= 1"),
                 "augment-huge": ("--augment", "1000000000", "<=")}
for _name, (_option, _value, _what) in TRAIN_OPTIONS.items():
    def _build(work, b, option=_option, value=_value, what=_what):
        argv, *_ = index_case(lambda rows, w: None, "")(work, b)
        return [*argv, option, value], option, what, [work / "run"]
    case(f"option-train-{_name}")(_build)


@case("csv-class-map-control")
def _(work, b):
    argv, *_ = score_case("ann", "id", "1", "")(work, b)
    return [*argv, "--classes", "1=cup\x1b[31m,4=glass,7=box"], "class mapping", "control", [work / "score.json"]


@case("index-image-header-bomb")
def _(work, b):
    argv, index, _, outputs = index_case(lambda rows, w: None, "")(work, b)
    (work / "patches" / "images" / "rec1_0.png").write_bytes(png_header_only(50_000, 50_000))
    return argv, work / "patches" / "images" / "rec1_0.png", "50000x50000", outputs



def _as_str(path) -> str:
    return str(path)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile_input(case, base, tmp_path, monkeypatch):
    monkeypatch.delenv("MASSVIZ_DEBUG", raising=False)
    work = tmp_path / "w"
    work.mkdir()
    argv, culprit, what, outputs = case.build(work, base)
    command = argv[0]
    before = snapshot(work, skip=work / "cache")
    code, stdout, stderr = run_cli(argv)
    lines = visible_lines(stderr)
    assert "Traceback" not in stderr + stdout and "internal error" not in stderr, stderr
    assert code == case.code, stderr
    assert len(lines) == 1, stderr
    prefix = f"massviz {command}: error: {culprit}"
    assert lines[0].startswith(prefix), (lines[0], prefix)
    assert re.search(what, lines[0][len(prefix):]), lines[0]
    assert not (work / "CANARY").exists(), "the hostile file ran code"
    for out in outputs:
        assert not Path(out).exists(), out
    assert snapshot(work, skip=work / "cache") == before, "something was written"
    assert not list((work / "cache").rglob("*.npz")) if (work / "cache").exists() else True


def test_enough_cases():
    assert len(CASES) >= 100


# ============================================================================================ accepted hostile inputs
@pytest.mark.slow
def test_partial_video_is_reported_and_allowed_on_request(base, tmp_path):
    """A video cut in half (index at the front): an error naming both counts by default; with --allow-partial the
    decoded frames are processed and the counts are on stderr and among the trace's events (Rerun's /log)."""
    from massviz.app import process
    from massviz.detect.saved import ReplayDetector
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.recording import open_recording

    rec = truncated_video(tmp_path)
    cap = cv2.VideoCapture(str(rec / "rgb.mp4"))
    decoded = 0
    while cap.grab():
        decoded += 1
    cap.release()
    assert 0 < decoded < 12 and int(cv2.VideoCapture(str(rec / "rgb.mp4")).get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    code, _, stderr = run_cli(estimate(tmp_path, base, rec)[0])
    assert code == 2 and f"only {decoded} of the 12 frames" in stderr and "--allow-partial" in stderr
    argv, out = estimate(tmp_path, base, rec, "--allow-partial")
    code, _, stderr = run_cli(argv)
    assert code == 0, stderr
    warning = [line for line in visible_lines(stderr) if "warning" in line]
    assert len(warning) == 1 and f"only {decoded} of the 12 frames" in warning[0] and str(rec / "rgb.mp4") in warning[0]
    assert out.is_file()
    opened = open_recording(rec, allow_partial=True)
    assert opened.num_frames == decoded and opened.declared_frames == 12
    trace = process(opened, ReplayDetector(base.replay), load_checkpoint(base.weights))
    assert [int(f) for f in trace.frames] == list(range(decoded))
    assert any(e.kind == "warning" and f"only {decoded} of the 12" in e.message for e in trace.events)
    rrd = tmp_path / "partial.rrd"
    code, _, stderr = run_cli(["log", rec, "--rrd", rrd, "--allow-partial", "--detector", "replay", "--replay",
                               base.replay, "--weights", base.weights, "--cache", tmp_path / "cache", "--quiet"])
    assert code == 0, stderr
    assert any(f"only {decoded} of the 12 frames" in t for t in rrd_log_texts(rrd))


def rrd_log_texts(path: Path) -> list[str]:
    """The ``/log`` TextLog lines of an .rrd file."""
    from rerun.chunk import RrdReader

    texts = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/log":
            batch = chunk.to_record_batch()
            for value in batch.column(batch.schema.names.index("TextLog:text")).to_pylist():
                texts.extend(value if isinstance(value, list) else [value])
    return [str(t) for t in texts]


def test_ids_from_data_files_are_sanitised_for_file_names(base, tmp_path):
    """A recording id that climbs out of the patch set (``../../x``) becomes a plain file name inside it."""
    rec = copy_sample(tmp_path / "rec")
    edit_json(rec / "meta.json", lambda d: d.update(id="../../../escaped/x"))
    before = {p for p in tmp_path.rglob("*")}
    out = tmp_path / "patches"
    code, _, stderr = run_cli(["extract", rec, "--out", out, "--detector", "replay", "--replay", base.replay,
                               "--weights", base.weights, "--cache", tmp_path / "cache", "--quiet", "--k", "1"])
    assert code == 0, stderr
    new = {p for p in tmp_path.rglob("*")} - before
    assert all(p == out or out in p.parents or tmp_path / "cache" in [p, *p.parents] for p in new), new
    images = sorted(p.name for p in (out / "images").iterdir())
    assert images == ["escaped_x_0.png"]
    import pandas as pd

    index = pd.read_csv(out / "index.csv")
    assert index["recording"].tolist() == ["../../../escaped/x"] and index["file"].tolist() == ["images/escaped_x_0.png"]


def test_id_with_comma_and_quote_is_quoted_in_the_challenge_csv(base, tmp_path):
    import csv

    rec = copy_sample(tmp_path / "rec")
    edit_json(rec / "meta.json", lambda d: d.update(id='cup, "large"'))
    argv, out = estimate(tmp_path, base, rec)
    code, _, stderr = run_cli(argv)
    assert code == 0, stderr
    with open(out, newline="") as f:
        rows = list(csv.reader(f))
    assert len(rows) == 2 and rows[1][0] == 'cup, "large"' and len(rows[1]) == 20


def _estimate_value(argv) -> str:
    code, _, stderr = run_cli(argv)
    assert code == 0, stderr
    return Path(argv[argv.index("--out") + 1]).read_text().splitlines()[1].split(",")[2]


@pytest.mark.slow
def test_same_size_edit_with_mtime_restored_is_not_served_from_the_cache(base, tmp_path):
    """The cache key is the files' content: an edit that keeps the size and sets the modification time back (what
    ``touch -d`` or a careless copy does) is seen, the detections are recomputed."""
    from massviz.io.cache import TraceCache
    from massviz.io.recording import open_recording

    rec = copy_sample(tmp_path / "rec")
    depth = rec / "depth" / "000001.png"
    d = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(depth), d, [cv2.IMWRITE_PNG_COMPRESSION, 0])  # uncompressed: the size depends only on W x H
    argv, out = estimate(tmp_path, base, rec, "--exact")
    first = _estimate_value(argv)
    key = TraceCache(tmp_path / "cache").entry(open_recording(rec), {}, 1)
    st = depth.stat()
    d[d > 0] = np.clip(d[d > 0].astype(np.int64) - 400, 1, None).astype(np.uint16)  # everything 40 cm nearer
    cv2.imwrite(str(depth), d, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    os.utime(depth, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert depth.stat().st_size == st.st_size and depth.stat().st_mtime_ns == st.st_mtime_ns
    assert TraceCache(tmp_path / "cache").entry(open_recording(rec), {}, 1) != key
    second = _estimate_value(argv)
    assert second != first  # d (a feature of the prediction) changed: not the stale cached value
    cached = _estimate_value(argv)
    assert cached == second


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["garbage", "truncated", "patch-not-png", "directory"])
def test_undecodable_cache_entry_is_dropped_and_recomputed(base, tmp_path, damage):
    rec = copy_sample(tmp_path / "rec")
    argv, out = estimate(tmp_path, base, rec, "--exact")
    first = _estimate_value(argv)
    (entry,) = (tmp_path / "cache" / "traces").rglob("t*.npz")
    data = entry.read_bytes()
    if damage == "garbage":
        entry.write_bytes(os.urandom(len(data)))
    elif damage == "truncated":
        entry.write_bytes(data[:len(data) // 2])
    elif damage == "patch-not-png":
        with np.load(entry) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["patch_bytes"] = np.zeros_like(arrays["patch_bytes"])
        np.savez(entry, **arrays)
    else:
        entry.unlink()
        entry.mkdir()
    code, _, stderr = run_cli(argv)
    assert code == 0 and visible_lines(stderr)[-1].startswith("wrote"), stderr
    assert _estimate_value(argv) == first
    assert entry.is_file()
    from massviz.io.trace_file import load_trace

    assert len(load_trace(entry).detections) == 1


def test_real_ccm_calibration_loads_through_the_restricted_unpickler(shared_dir):
    from massviz.io.untrusted import RestrictedUnpickler, load_calibration_pickle

    path = shared_dir / "ccm_real" / "view1" / "calib" / "000000.pickle"
    calib = load_calibration_pickle(path)
    assert calib[0]["rgb"][0, 0] == pytest.approx(923.62, abs=0.01)
    for protocol in range(6):  # the same data re-saved by Python 3 / numpy 2 in every protocol
        again = RestrictedUnpickler(io.BytesIO(pickle.dumps(calib, protocol=protocol))).load()
        np.testing.assert_array_equal(again[1]["rgb"]["projMatrix"], calib[1]["rgb"]["projMatrix"])


# ===================================================================================================== subprocesses
SUBPROCESS = ["calib-os_system_p0", "video-cut-in-half", "output-estimate-out-is-dir", "option-render-yaw-nan",
              "meta-id_escape", "replay-mask_parent"]


@pytest.mark.slow
def test_as_real_subprocesses(base, tmp_path):
    """A few cases as a user runs them: ``python -m massviz ...``, two at a time."""
    from concurrent.futures import ThreadPoolExecutor

    by_name = {c.name: c for c in CASES}
    jobs = []
    for name in SUBPROCESS:
        work = tmp_path / name
        work.mkdir()
        argv, culprit, what, outputs = by_name[name].build(work, base)
        jobs.append((name, work, argv, culprit, what, outputs, snapshot(work, skip=work / "cache")))

    def call(job):
        return run_massviz(*job[2], timeout=300)

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(call, jobs))
    for (name, work, argv, culprit, what, outputs, before), result in zip(jobs, results, strict=False):
        stderr = result.stderr
        lines = visible_lines(stderr)
        assert result.returncode == 2 and "Traceback" not in stderr and len(lines) == 1, (name, stderr)
        prefix = f"massviz {argv[0]}: error: {culprit}"
        assert lines[0].startswith(prefix) and re.search(what, lines[0][len(prefix):]), (name, lines[0])
        assert not (work / "CANARY").exists() and not any(Path(o).exists() for o in outputs), name
        assert snapshot(work, skip=work / "cache") == before, name

