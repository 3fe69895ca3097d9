"""Hostile inputs beyond test_hostile_inputs.py's, each in a process of its own: numbers the JSON parser refuses, checkpoints that compute inf/NaN,
outputs that are not regular files, a full disk, signals, terminal escapes, compression bombs, scores and tables,
trace files from elsewhere, arguments.

Every case runs ``massviz`` in a process of its own (its peak RSS sampled, its wall time bounded): the first case of
each class, and every case with a signal or a resource limit, as a real ``python -m massviz`` subprocess; the others
forked from a server that imported massviz and torch once (``tests/forkserver.py``: the same ``main``, environment,
folder, files and exit; 2-3 s less per case). Each is held to the same promise (``hostile_runs.check_promise``): the
expected
exit code, exactly one error line naming the right file and saying what is wrong, no traceback / internal error, no
non-finite number in stdout, stderr or any file written, nothing left in or beside the outputs (no hidden
temporaries), nothing written outside the case's folder (its TMPDIR stays empty), no raw control character on the
terminal, peak memory under ``MEM_BOUND_MB`` and wall time under ``TIME_BOUND_S``. Cases are generated per class
(parametrised generators), each with its runner (``subprocess`` or ``forked``); they start massviz processes, so they
are ``slow``. The last tests call the library on the same fixtures: only massviz's error types may come out.
"""
from __future__ import annotations

import json
import os
import re
import resource
import shutil
import signal
import stat
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from fakes import ANN_HEADER, ANN_ROWS, PRED_HEADER, PRED_ROWS, Base, copy_sample, csv_text
from forkserver import ForkServer
from hostile_runs import (
    MEM_BOUND_MB,
    RAW_CONTROL,
    Case,
    Run,
    check_promise,
    clean_env,
    folder_state,
    pipeline_argv,
    run_massviz,
)

ROOT = Path(__file__).resolve().parents[1]


# ============================================================================================================= bases
# ``base`` (a 3-frame copy of the cup sample, random-weight checkpoint, replay JSON, a saved trace): conftest.py.



# ============================================================================================================ class 1
def big_int(digits: int) -> str:
    return "9" * digits


def deep(n: int, kind: str = "[") -> str:
    if kind == "[":
        return "[" * n + "]" * n
    return '{"a":' * n + "1" + "}" * n


JSON_PAYLOADS = {"int5000": big_int(5000), "int4301neg": "-" + big_int(4301), "deep100k-list": deep(100_000),
                 "deep100k-object": deep(100_000, "{"), "deep65-list": deep(65)}
JSON_WHAT = r"digits|deep|not valid JSON"


def json_case(target: str, payload_name: str) -> Callable[[Path, Base], Case]:
    payload = JSON_PAYLOADS[payload_name]

    def build(work: Path, b: Base) -> Case:
        rec = copy_sample(work / "rec")
        out = work / "preds.csv"
        if target in ("meta", "intrinsics"):
            path = rec / f"{target}.json"
            data = json.loads(path.read_text())
            key = "fps" if target == "meta" else "fx"
            data[key] = "@@"
            path.write_text(json.dumps(data).replace('"@@"', payload))
            return Case("", pipeline_argv(work, b, "estimate", rec, "--out", out), path, JSON_WHAT, [out])
        if target == "sidecar":
            import torch

            ckpt = work / "ckpt.torch"
            p = torch.load(b.weights, weights_only=True)
            del p["ranges"]
            p["state_dict"]["linear3.bias"] += 1
            torch.save(p, ckpt)
            side = work / "ckpt.torch.ranges.json"
            side.write_text('{"minMass": %s, "maxMass": 200}' % payload)
            return Case("", pipeline_argv(work, b, "estimate", rec, "--out", out, weights=ckpt), side, JSON_WHAT,
                        [out])
        if target == "classmap":
            ann, pred, cmap = work / "ann.csv", work / "pred.csv", work / "classes.json"
            ann.write_text(csv_text(ANN_HEADER, ANN_ROWS))
            pred.write_text(csv_text(PRED_HEADER, PRED_ROWS))
            cmap.write_text('{"1": %s}' % payload)
            js = work / "score.json"
            return Case("", ["score", pred, "--annotations", ann, "--classes", cmap, "--json", js], cmap, JSON_WHAT,
                        [js])
        if target == "exclusions":
            path = work / "exclude.json"
            path.write_text('{"format": "massviz.exclusions/1", "exclusions": [{"frame": %s}]}' % payload)
            return Case("", pipeline_argv(work, b, "estimate", rec, "--out", out, "--exclude", path), path,
                        JSON_WHAT, [out])
        if target == "replay":
            path = work / "replay.json"
            path.write_text('{"detections": [{"frame": %s, "box": [1, 2, 3, 4]}]}' % payload)
            return Case("", pipeline_argv(work, b, "estimate", rec, "--out", out, replay=path), path, JSON_WHAT,
                        [out])
        raise AssertionError(target)
    return build


# ============================================================================================================ class 2
def _ckpt(make):
    def build(work: Path, b: Base) -> Path:
        import torch

        payload = torch.load(b.weights, weights_only=True)
        make(payload)
        path = work / "ckpt.torch"
        torch.save(payload, path)
        return path
    return build


CHECKPOINTS = {
    "span-tiny": (lambda p: p["ranges"].update(minMass=1.0, maxMass=1.0 + 1e-9), "spans"),
    "span-huge": (lambda p: p["ranges"].update(minAverageDistance=-1e300, maxAverageDistance=1e300), "beyond"),
    "ratio-span-tiny": (lambda p: p["ranges"].update(minRatioWidth=0.5, maxRatioWidth=0.5 + 1e-12), "spans"),
    "bn-negative-var": (lambda p: p["state_dict"]["bn1.running_var"].__setitem__(0, -4.0), "negative variance"),
    "float64-1e300": (lambda p: p["state_dict"].update(
        {"linear3.weight": p["state_dict"]["linear3.weight"].double().fill_(1e300)}), "NaN or infinite|beyond"),
    "weights-huge": (lambda p: p["state_dict"]["linear1.weight"].mul_(1e10), "beyond"),
    "bn1-mean-float64-1e39": (lambda p: p["state_dict"].update(
        {"bn1.running_mean": p["state_dict"]["bn1.running_mean"].double().fill_(1e39)}), "NaN or infinite"),
}


def checkpoint_case(name: str, command: str) -> Callable[[Path, Base], Case]:
    make, what = CHECKPOINTS[name]

    def build(work: Path, b: Base) -> Case:
        rec = copy_sample(work / "rec")
        ckpt = _ckpt(make)(work, b)
        if command == "estimate":
            out = work / "preds.csv"
            argv = pipeline_argv(work, b, "estimate", rec, "--out", out, weights=ckpt)
        elif command == "log":
            out = work / "o.rrd"
            argv = pipeline_argv(work, b, "log", rec, "--rrd", out, weights=ckpt)
        else:
            out = work / "patches"
            argv = pipeline_argv(work, b, "extract", rec, "--out", out, weights=ckpt)
        return Case("", argv, ckpt, what, [out])
    return build


# ============================================================================================================ class 3
def _special(kind: str, path: Path) -> Path:
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "chardev":  # a /dev/null-like node of our own, never /dev/full itself
        os.mknod(path, 0o600 | stat.S_IFCHR, os.makedev(1, 3))
    elif kind == "link-to-chardev":
        dev = path.with_name(path.name + ".dev")
        os.mknod(dev, 0o600 | stat.S_IFCHR, os.makedev(1, 3))
        os.symlink(dev.name, path)
    elif kind == "link-to-fifo":
        fifo = path.with_name(path.name + ".fifo")
        os.mkfifo(fifo)
        os.symlink(fifo.name, path)
    elif kind == "link-loop":
        os.symlink(path.name, path)
    else:
        raise AssertionError(kind)
    return path


SPECIAL_WHAT = r"character device|FIFO|symlink|Too many levels"
OUTPUT_OPTIONS = {
    "estimate-out": lambda w, b, p: pipeline_argv(w, b, "estimate", copy_sample(w / "rec"), "--out", p),
    "log-rrd": lambda w, b, p: pipeline_argv(w, b, "log", copy_sample(w / "rec"), "--rrd", p),
    "score-json": lambda w, b, p: ["score", _csv(w / "pred.csv", PRED_HEADER, PRED_ROWS), "--annotations",
                                   _csv(w / "ann.csv", ANN_HEADER, ANN_ROWS), "--json", p],
    "compare-json": lambda w, b, p: ["compare", b.trace_npz, b.trace_npz, "--json", p],
}


def _csv(path: Path, header, rows) -> Path:
    path.write_text(csv_text(header, rows))
    return path


def output_case(option: str, kind: str) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        suffix = {"log-rrd": ".rrd", "estimate-out": ".csv"}.get(option, ".json")
        target = _special(kind, work / f"out{suffix}")
        return Case("", OUTPUT_OPTIONS[option](work, b, target), target, SPECIAL_WHAT)
    return build


# ============================================================================================================ class 4
def _fsize_limit(nbytes: int) -> Callable:
    def limit():  # Python ignores SIGXFSZ: a write beyond the limit fails with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return limit


def disk_full_case(command: str, limit: int) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        rec = copy_sample(work / "rec")
        # the cache's writes are not the case: --no-cache
        if command == "log":
            out = work / "o.rrd"
            argv = pipeline_argv(work, b, "log", rec, "--rrd", out, cache=False)
        elif command == "cloud":
            out = work / "clouds"
            argv = pipeline_argv(work, b, "cloud", rec, "--out", out, "--all-frames", cache=False)
        else:
            out = work / "patches"
            argv = pipeline_argv(work, b, "extract", rec, "--out", out, cache=False)
        return Case("", argv, out, r"(File too large|No space left|cannot write)", [out], preexec=_fsize_limit(limit))
    return build


# ============================================================================================================ class 5
def handles_signal(pid: int, sig: int) -> bool:
    """Whether process ``pid`` runs and has a handler installed for ``sig`` (Linux: the SigCgt mask in
    /proc/PID/status; a process that has ended but is not yet waited for keeps its mask)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    if re.search(r"^State:\s*[ZX]", status, re.M):
        return False
    caught = re.search(r"^SigCgt:\s*([0-9a-f]+)", status, re.M)
    return bool(caught) and bool(int(caught.group(1), 16) >> (sig - 1) & 1)


def signal_case(command: str, sig: int) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        rec = copy_sample(work / "rec", n=12)
        if command == "log":
            out = work / "o.rrd"
            argv = pipeline_argv(work, b, "log", rec, "--rrd", out)
        elif command == "cloud":
            out = work / "clouds"
            argv = pipeline_argv(work, b, "cloud", rec, "--out", out, "--all-frames")
        else:
            out = work / "patches"
            argv = pipeline_argv(work, b, "extract", rec, "--out", out)

        def writing(pid: int) -> bool:
            # as soon as massviz has installed its handler for the signal (/proc's SigCgt mask), while it still
            # imports and runs: a replayed 12-frame run is over within ~1 s, and extract writes its folder in one go
            # at the very end, so waiting for the output to appear raced the command's end (flaky)
            return handles_signal(pid, sig)
        writing.takes_pid = True
        name = signal.Signals(sig).name
        return Case("", argv, None, rf"\({name}\)" if sig != signal.SIGINT else "$", [out], code=128 + sig,
                    line="interrupted", when=writing, send=sig)
    return build


# ============================================================================================================ class 7
ESCAPES = {"osc-title": "\x1b]0;pwned\x07", "clear": "\x1b[2J", "csi-c1": "\x9b31m", "rtl": "\u202e", "cr": "\r"}


def escape_case(where: str, esc: str) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        seq = ESCAPES[esc]
        if where == "folder":  # the id comes from the folder name; the error (no depth) prints it
            rec = copy_sample(work / f"rec{seq}x")
            shutil.rmtree(rec / "depth")
            out = work / "preds.csv"
            from massviz.io.untrusted import printable

            return Case("", pipeline_argv(work, b, "estimate", rec, "--out", out), printable(rec), r".", [out])
        # a trace file whose recording id carries the sequence
        from massviz.io.untrusted import load_npz_checked

        arrays = load_npz_checked(b.trace_npz)
        header = json.loads(arrays["header"].tobytes())
        header["recording"]["id"] = f"cup{seq}x"
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
        path = work / "t.npz"
        np.savez_compressed(path, **arrays)
        js = work / "c.json"
        return Case("", ["compare", path, b.trace_npz, "--json", js], path, r"control|recording", [js])
    return build


# ============================================================================================================ class 9
def npz_bomb(path: Path, inflated: int, members: int = 1) -> Path:
    """An .npz whose uint8 members declare honestly (the .npy header matches) and inflate ~1000:1."""
    chunk = bytes(1 << 20)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for m in range(members):
            with z.open(f"det_pred{m or ''}.npy", "w", force_zip64=True) as fh:
                header = {"descr": "|u1", "fortran_order": False, "shape": (inflated,)}
                np.lib.format.write_array_header_1_0(fh, header)
                left = inflated
                while left:
                    n = min(left, len(chunk))
                    fh.write(chunk[:n])
                    left -= n
    return path


BOMBS = {"300MB": (300 << 20, 1), "2x400MB": (400 << 20, 2), "3MB": (3 << 20, 1)}


def bomb_case(use: str, bomb: str) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        size, members = BOMBS[bomb]
        path = npz_bomb(work / "bomb.npz", size, members)
        if use == "replay":
            out = work / "preds.csv"
            return Case("", pipeline_argv(work, b, "estimate", copy_sample(work / "rec"), "--out", out,
                                          replay=path), path, r"bomb|inflate|not a massviz trace", [out])
        js = work / "c.json"
        return Case("", ["compare", path, b.trace_npz, "--json", js], path, r"bomb|inflate|not a massviz trace", [js])
    return build


# =========================================================================================================== class 10
def table_case(name: str) -> Callable[[Path, Base], Case]:
    def build(work: Path, b: Base) -> Case:
        ann, pred, js = work / "ann.csv", work / "pred.csv", work / "score.json"
        ann_rows, pred_rows, ann_header, pred_header = list(ANN_ROWS), list(PRED_ROWS), ANN_HEADER, PRED_HEADER
        culprit, what, extra = ann, "", []
        if name.startswith("tiny-mass-"):
            ann_rows[1] = ann_rows[1].rsplit(",", 1)[0] + "," + name.split("-", 2)[2]
            what = r"container mass.*>= 0.001"
        elif name.startswith("huge-pred-"):
            pred_rows[1] = "1," + name.split("-", 2)[2]
            culprit, what = pred, r"Container mass.*beyond"
        elif name == "dup-column-ann":
            ann_header += ",container mass"
            ann_rows = [r + ",5" for r in ann_rows]
            what = r"appears twice"
        elif name == "dup-column-pred":
            pred_header += ",Configuration ID"
            pred_rows = [r + ",9" for r in pred_rows]
            culprit, what = pred, r"appears twice"
        elif name == "container-without-class":
            ann_rows[1] = "1,42," + ann_rows[1].split(",", 2)[2]
            what = r"container 42 has no class"
        ann.write_text(csv_text(ann_header, ann_rows))
        pred.write_text(csv_text(pred_header, pred_rows))
        return Case("", ["score", pred, "--annotations", ann, "--json", js, *extra], culprit, what, [js])
    return build


# =========================================================================================================== class 11
TRACE_EDITS = {
    "detector-list": (lambda h: h.__setitem__("detector", ["depth"]), "detector"),
    "timings-text": (lambda h: h.__setitem__("timings", {"read": "fast"}), "timings"),
    "fps-text": (lambda h: h["recording"].__setitem__("fps", "thirty"), "fps"),
    "intrinsics-nan": (lambda h: h["recording"].__setitem__("intrinsics", {"fx": float("nan"), "fy": 1, "cx": 1,
                                                                           "cy": 1, "width": 4, "height": 4}), "fx"),
    "events-object": (lambda h: h.__setitem__("events", [{"frame": 1}]), "events"),
    "weights-id-number": (lambda h: h.__setitem__("weights_id", 12), "weights_id"),
    "stages-dict": (lambda h: h.__setitem__("frame_timing_stages", {"a": 1}), "frame_timing_stages"),
}


def trace_case(edit: str, use: str) -> Callable[[Path, Base], Case]:
    fn, what = TRACE_EDITS[edit]

    def build(work: Path, b: Base) -> Case:
        from massviz.io.untrusted import load_npz_checked

        arrays = load_npz_checked(b.trace_npz)
        header = json.loads(arrays["header"].tobytes())
        fn(header)
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)  # NaN written as NaN: hostile
        path = work / "t.npz"
        np.savez_compressed(path, **arrays)
        if use == "compare":
            js = work / "c.json"
            return Case("", ["compare", path, b.trace_npz, "--json", js], path, what, [js])
        if use == "replay":
            out = work / "preds.csv"
            return Case("", pipeline_argv(work, b, "estimate", copy_sample(work / "rec"), "--out", out, replay=path),
                        path, what, [out])
        out = work / "o.rrd"
        return Case("", pipeline_argv(work, b, "log", copy_sample(work / "rec"), "--rrd", out, replay=path), path,
                    what, [out])
    return build


# =========================================================================================================== class 12
ARGUMENTS = {
    "threads-2^70": (lambda w, b: pipeline_argv(w, b, "estimate", copy_sample(w / "rec"), "--out", w / "p.csv",
                                                "--threads", str(2**70)), "--threads"),
    "threads-0": (lambda w, b: pipeline_argv(w, b, "estimate", copy_sample(w / "rec"), "--out", w / "p.csv",
                                             "--threads", "0"), "--threads"),
    "stride-2^64": (lambda w, b: pipeline_argv(w, b, "estimate", copy_sample(w / "rec"), "--out", w / "p.csv",
                                               "--stride", str(2**64)), "--stride"),
    "train-seed-2^70": (lambda w, b: ["train", w, "--out", w / "run", "--seed", str(2**70)], "--seed"),
    "train-seed--1": (lambda w, b: ["train", w, "--out", w / "run", "--seed=-1"], "--seed"),
    "baseline-seed-2^40": (lambda w, b: ["baseline", "random", "--annotations", _csv(w / "a.csv", ANN_HEADER,
                                                                                     ANN_ROWS),
                                         "--seed", str(2**40), "--out", w / "m4.csv"], "--seed"),
    "sweep-10^8-pairs": (lambda w, b: ["sweep", copy_sample(w / "rec"), "--threshold", "0:0.9999:0.0001",
                                       "--k", "1:10000", "--csv", w / "s.csv"], "--threshold"),
}


def argument_case(name: str) -> Callable[[Path, Base], Case]:
    make, option = ARGUMENTS[name]

    def build(work: Path, b: Base) -> Case:
        return Case("", make(work, b), option, r"integer in|pairs|at most")
    return build


# ============================================================================================================ cases
def _classes() -> dict[str, list[tuple[str, Callable]]]:
    classes: dict[str, list[tuple[str, Callable]]] = {}
    classes["1-json"] = [(f"json-{t}-{p}", json_case(t, p))
                         for t in ("meta", "intrinsics", "sidecar", "classmap", "exclusions", "replay")
                         for p in JSON_PAYLOADS]
    classes["2-checkpoint"] = [(f"ckpt-{n}-{c}", checkpoint_case(n, c)) for n in CHECKPOINTS
                               for c in ("estimate", "log", "extract")]
    classes["3-output"] = [(f"output-{o}-{k}", output_case(o, k)) for o in OUTPUT_OPTIONS
                           for k in ("chardev", "fifo", "link-to-chardev", "link-to-fifo", "link-loop")]
    # the limit must be below what the command writes: a one-patch extract of this sample writes about 1 KiB
    classes["4-disk-full"] = [(f"disk-full-{c}-{n}", disk_full_case(c, n)) for c in ("log", "cloud", "extract")
                              for n in ((512, 256) if c == "extract" else (4096, 256))]
    classes["5-signal"] = [(f"signal-{c}-{signal.Signals(s).name}", signal_case(c, s))
                           for c in ("log", "extract", "cloud") for s in (signal.SIGTERM, signal.SIGHUP)]
    classes["7-escape"] = [(f"escape-{w}-{e}", escape_case(w, e)) for w in ("folder", "trace") for e in ESCAPES]
    classes["9-bomb"] = [(f"bomb-{u}-{n}", bomb_case(u, n)) for n in ("300MB", "2x400MB") for u in ("replay", "compare")]
    classes["10-table"] = [(f"table-{n}", table_case(n)) for n in
                           ("tiny-mass-1e-300", "tiny-mass-5e-324", "tiny-mass-0.0001", "huge-pred-1e300",
                            "huge-pred-1e12", "dup-column-ann", "dup-column-pred", "container-without-class")]
    classes["11-trace"] = [(f"trace-{e}-{u}", trace_case(e, u)) for e in TRACE_EDITS for u in ("compare", "replay",
                                                                                                "log")]
    classes["12-argument"] = [(f"arg-{n}", argument_case(n)) for n in ARGUMENTS]
    return classes


CLASSES = _classes()
#: every generated case, with its runner: the first of each class a real subprocess, the others forked (a case with a
#: signal or a resource limit is a subprocess whatever its runner); all start massviz processes, so all are ``slow``
PARAMS = [pytest.param(build, "subprocess" if i == 0 else "forked", id=name, marks=pytest.mark.slow)
          for cases in CLASSES.values() for i, (name, build) in enumerate(cases)]


@pytest.fixture(scope="module")
def fork_server():
    """One fork server per worker for the generated cases after the first of each class (``tests/forkserver.py``)."""
    server = ForkServer({**clean_env(), "PYTHONPATH": str(ROOT)})
    yield server
    server.close()


@pytest.mark.parametrize("build,runner", PARAMS)
def test_hostile_input_in_a_process_of_its_own(build, runner, base, tmp_path, request):
    """A ``subprocess`` case runs as a real ``python -m massviz`` subprocess; a ``forked`` one is forked from a
    server that imported massviz and torch once, unless it needs a signal or a resource limit."""
    work = tmp_path / "w"
    work.mkdir()
    (work / "home").mkdir()
    case = build(work, base)
    case.name = request.node.callspec.id
    before = folder_state(work, tuple(work / w for w in ("cache", "usercache", "xdg", "home", "tmpdir")) + tuple(case.writes))
    forked = request.getfixturevalue("fork_server") if runner == "forked" else None
    for attempt in range(1, 4):
        run = run_massviz(case.argv, work, preexec=case.preexec, when=case.when, send=case.send, forked=forked)
        if case.send is None or run.signalled:
            break
        # the command ended before the test's thread got to send the signal (a starved thread on a loaded
        # machine): nothing was tested; run the case again in a new folder
        work = tmp_path / f"w{attempt}"
        work.mkdir()
        (work / "home").mkdir()
        case = build(work, base)
        case.name = request.node.callspec.id
        before = folder_state(work, tuple(work / w for w in ("cache", "usercache", "xdg", "home", "tmpdir"))
                          + tuple(case.writes))
    assert case.send is None or run.signalled, f"{case.name}: the command ended before the signal, three times"
    check_promise(case, run, work, before)


@pytest.mark.slow
@pytest.mark.parametrize("cls", ["1-json", "2-checkpoint", "11-trace"])
def test_a_forked_run_equals_a_subprocess_run(cls, base, fork_server, tmp_path):
    """The fork server is held to what it stands in for: the same case (the second of a class) run both ways gives
    the same exit code, stdout, stderr and files."""
    name, build = CLASSES[cls][1]
    runs, trees = [], []
    for how in ("subprocess", "forked"):
        work = tmp_path / how / "w"
        work.mkdir(parents=True)
        (work / "home").mkdir()
        case = build(work, base)
        run = run_massviz(case.argv, work, forked=fork_server if how == "forked" else None)
        runs.append((run.code, run.stdout.replace(str(work), "W"), run.stderr.replace(str(work), "W")))
        trees.append({k: v[:2] for k, v in folder_state(work, (work / "usercache", work / "xdg")).items()})
    assert runs[0] == runs[1], (name, runs)
    assert trees[0] == trees[1], name
    assert runs[0][0] != 0 and runs[0][2].strip(), (name, runs[0])  # a hostile case: it failed, and said so


def test_enough_generated_cases():
    assert len(PARAMS) >= 120 and all(len(cases) >= 4 for cases in CLASSES.values())


# ======================================================================================== accepted hostile inputs
@pytest.mark.slow  # a massviz subprocess
def test_output_symlink_is_written_through_and_kept(base, tmp_path):
    """A symlink as --out: the file it points to gets the CSV, the link stays a link (never replaced)."""
    work = tmp_path / "w"
    work.mkdir()
    target = work / "real.csv"
    target.write_text("old\n")
    link = work / "link.csv"
    link.symlink_to(target.name)
    run = run_massviz(pipeline_argv(work, base, "estimate", copy_sample(work / "rec"), "--out", link), work)
    assert run.code == 0, run.stderr
    assert link.is_symlink() and os.readlink(link) == target.name
    assert target.read_text().startswith("Configuration ID")
    assert not [p for p in work.iterdir() if p.name.startswith(".")], "hidden temporary left"


@pytest.mark.slow  # a massviz subprocess
def test_formula_ids_are_neutralised_in_csvs(base, tmp_path):
    """A recording id starting with '=' goes into the challenge CSV as text ("'=..."), matching on the raw id."""
    work = tmp_path / "w"
    work.mkdir()
    rec = copy_sample(work / "rec")
    meta = json.loads((rec / "meta.json").read_text())
    meta["id"] = "=HYPERLINK(\"http://x\")"
    meta.pop("config_id", None)
    (rec / "meta.json").write_text(json.dumps(meta))
    out = work / "p.csv"
    run = run_massviz(pipeline_argv(work, base, "estimate", rec, "--out", out), work)
    assert run.code == 0, run.stderr
    cells = [line.split(",")[0] for line in out.read_text().splitlines()[1:]]
    assert cells and all(not c.lstrip('"').startswith(("=", "+", "-", "@")) for c in cells), cells
    from massviz.io.untrusted import csv_cell

    assert csv_cell("=1+2") == "'=1+2" and csv_cell("-1") == "-1" and csv_cell("@x") == "'@x" and csv_cell(7) == 7


@pytest.mark.slow  # more than ~3 s on 2 idle cores (a massviz subprocess or a pipeline run)
def test_cache_memo_nested_deep_is_recomputed(base, tmp_path):
    """A digest memo of the cache nested 100,000 deep (or with a 5,000-digit integer) is dropped and rewritten."""
    work = tmp_path / "w"
    work.mkdir()
    rec = copy_sample(work / "rec")
    argv = pipeline_argv(work, base, "estimate", rec, "--out", work / "p.csv")
    assert run_massviz(argv, work).code == 0
    memos = list((work / "cache").rglob("hashes/*.json"))
    assert memos
    for i, memo in enumerate(memos):
        memo.write_text(deep(100_000) if i % 2 == 0 else '{"x": %s}' % big_int(5000))
    run = run_massviz(argv, work)
    assert run.code == 0 and "Traceback" not in run.stderr, run.stderr
    assert run.peak_mb < MEM_BOUND_MB


@pytest.mark.slow  # more than ~3 s on 2 idle cores (a massviz subprocess or a pipeline run)
def test_deflate_bomb_in_the_cache_is_dropped(base, tmp_path):
    """A cache entry replaced by a 300 MB deflate bomb: dropped and recomputed within the memory bound."""
    work = tmp_path / "w"
    work.mkdir()
    argv = pipeline_argv(work, base, "estimate", copy_sample(work / "rec"), "--out", work / "p.csv", "--exact")
    assert run_massviz(argv, work).code == 0
    def masses():  # the estimate column (the execution time differs between runs)
        return [line.split(",")[2] for line in (work / "p.csv").read_text().splitlines()]
    first = masses()
    (entry,) = (work / "cache" / "traces").rglob("t*.npz")
    npz_bomb(entry, 300 << 20)
    run = run_massviz(argv, work)
    assert run.code == 0 and run.peak_mb < MEM_BOUND_MB, (run.stderr, run.peak_mb)
    assert masses() == first


def test_printable_escapes_every_control_character():
    from massviz.io.untrusted import printable

    for seq in ESCAPES.values():
        text = printable(f"a{seq}b")
        assert not RAW_CONTROL.search(text) and "\r" not in text and text.startswith("a") and text.endswith("b")
    assert printable("line\nnext", keep="\n") == "line\nnext"



TRAIN_CASES = {
    "lr-10": (lambda w, p, b: ["--lr", "10", "--epochs", "40"], lambda w, p: "training stopped:",
              r"(loss|weight).*lower --lr"),
    "init-nan-bn": (lambda w, p, b: ["--init", _ckpt(CHECKPOINTS["bn-negative-var"][0])(w, b)],
                    lambda w, p: w / "ckpt.torch", "negative variance"),
    "patch-truncated": (lambda w, p, b: _damage_patch(p, w, b"\x89PNG\r\n\x1a\n\x00\x00"), None, "cannot be read"),
    "patch-not-image": (lambda w, p, b: _damage_patch(p, w, b"hello, not a png"), None, "cannot be read"),
    "device-mps": (lambda w, p, b: ["--device", "mps"], lambda w, p: "--device", "not available|mps"),
}


def _damage_patch(patches: Path, work: Path, data: bytes) -> list:
    copy = work / "patches"
    shutil.copytree(patches, copy)
    first = sorted((copy / "images").iterdir())[0]
    first.write_bytes(data)
    return []


@pytest.mark.slow
@pytest.mark.parametrize("name", list(TRAIN_CASES))
def test_train_stops_cleanly(name, base, sample_patch_set, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    extra_of, culprit_of, what = TRAIN_CASES[name]
    extra = extra_of(work, sample_patch_set, base)
    patches = work / "patches" if (work / "patches").exists() else sample_patch_set
    culprit = culprit_of(work, patches) if culprit_of else next(p for p in sorted((patches / "images").iterdir()))
    argv = ["train", patches, "--out", work / "run", "--epochs", "2", "--augment", "1", "--quiet", *map(str, extra)]
    case = Case(name, argv, culprit, what, [work / "run"])
    before = folder_state(work)
    check_promise(case, run_massviz(argv, work), work, before)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_train_signal_leaves_no_run_folder(sig, base, sample_patch_set, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    out = work / "run"
    argv = ["train", sample_patch_set, "--out", out, "--epochs", "200", "--augment", "1", "--quiet"]
    name = signal.Signals(sig).name

    def training() -> bool:
        return any(p.name.startswith(".mv-") and (p / "metrics.csv").exists() for p in work.iterdir())
    case = Case(f"train-{name}", argv, None, rf"\({name}\)" if sig != signal.SIGINT else "$", [out],
                code=128 + sig, line="interrupted", when=training, send=sig)
    before = folder_state(work)
    check_promise(case, run_massviz(argv, work, when=training, send=sig), work, before)


# ================================================================================= slow: signals during live --save
#: the frames of the cup sample a live case plays (the container comes nearest in 19..29), eight times over, at
#: 10 fps: real-time playback takes 9.6 s, so a signal sent once the first frame is saved arrives mid-session even
#: on loaded cores (with 3.6 s, a load of 9 on 2 cores once let the file end first).
LIVE_FRAMES = list(range(18, 30)) * 8


@pytest.fixture(scope="module")
def live_db3(tmp_path_factory) -> Path:
    from fakes import need_realsense

    need_realsense()
    from fakes import write_recording
    from massviz.io.formats.realsense_write import write_realsense
    from massviz.io.recording import open_recording

    sample = open_recording(ROOT / "data_samples" / "cup_handover")
    frames = {f.index: f for f in sample.frames(indices=sorted(set(LIVE_FRAMES)))}
    root = tmp_path_factory.mktemp("hostile_live")
    folder = write_recording(root / "played", [frames[i].rgb for i in LIVE_FRAMES],
                             [frames[i].depth for i in LIVE_FRAMES], intrinsics=sample.intrinsics.to_dict(),
                             meta={"id": "played", "fps": 10})
    return write_realsense(open_recording(folder), root / "played.db3", pace=True)


def live_signal_case(sig: int, outputs: str, when: str) -> Callable[[Path, Base, Path], Case]:
    """``massviz live --file X.db3 --save REC [--rrd OUT.rrd]`` sent ``sig``: ``when="session"`` once the first frame
    is in --save's hidden folder (the session runs: it ends as Ctrl-C ends it, exit 0, every output complete and
    valid), ``when="start"`` once massviz's handlers are installed (it is still loading: interrupted, exit 128 +
    the signal, no output); ``when="twice"``: mid-session, SIGHUP then ``sig`` delivered together (sent while the
    process is stopped; Python runs the handlers in signal-number order): the second interrupts at once, no output.
    """
    name = signal.Signals(sig).name

    def build(work: Path, b: Base, db3: Path) -> Case:
        save, rrd = work / "rec", work / "live.rrd"
        outs = [save] + ([rrd] if outputs == "save+rrd" else [])
        argv = ["live", "--file", db3, "--save", save, *(["--rrd", rrd] if rrd in outs else []),
                "--detector", "depth", "--weights", b.weights, "--cache", work / "cache", "--quiet"]
        def recording() -> bool:
            return any(work.glob(".mv-*/rgb/*.png"))

        if when == "twice":
            def two(pid: int) -> bool:
                if not recording():
                    return False
                for first in (signal.SIGSTOP, signal.SIGHUP, sig):
                    os.kill(pid, first)
                return True  # then SIGCONT: both arrive at once
            two.takes_pid = True
            return Case("", argv, None, rf"\({name}\)", outs, code=128 + sig, line="interrupted", when=two,
                        send=signal.SIGCONT)
        if when == "start":
            def loading(pid: int) -> bool:  # massviz.cli's handlers are in (SIGINT's is Python's from the start)
                return handles_signal(pid, signal.SIGTERM)
            loading.takes_pid = True
            return Case("", argv, None, rf"\({name}\)" if sig != signal.SIGINT else "$", outs, code=128 + sig,
                        line="interrupted", when=loading, send=sig)

        def complete(case: Case, run: Run) -> None:
            from massviz.io.recording import open_recording
            from rrd_reader import rrd_entities

            how = "" if sig == signal.SIGINT else f" ({name})"
            assert f"stopped: interrupted{how}\n" in run.stderr, f"{case.name}: not ended by the signal: {run.stderr}"
            rec = open_recording(save)
            frames = list(rec.frames())
            live = rec.meta["live"]
            assert 1 <= len(frames) == rec.num_frames == live["processed"] < len(LIVE_FRAMES), (case.name, live)
            assert live["stopped"] == f"interrupted{how}"
            if rrd in outs:
                assert {"/camera/rgb", "/predictions/running_estimate", "/summary"} <= rrd_entities(rrd)
        return Case("", argv, None, "", [], code=0, line="", writes=tuple(outs), when=recording, send=sig,
                    check=complete)
    return build


LIVE_SIGNAL_CASES = {f"signal-live-{o}-{signal.Signals(s).name}-{w}": live_signal_case(s, o, w)
                     for w in ("session", "start") for o in ("save", "save+rrd")
                     for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)}
LIVE_SIGNAL_CASES.update({f"signal-live-{o}-SIGHUP+SIGTERM-twice": live_signal_case(signal.SIGTERM, o, "twice")
                          for o in ("save", "save+rrd")})


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LIVE_SIGNAL_CASES))
def test_live_signal(name, base, live_db3, tmp_path):
    """SIGTERM, SIGHUP and SIGINT during ``massviz live --save`` (and ``--rrd``): held to the same promise."""
    work = tmp_path / "w"
    work.mkdir()
    (work / "home").mkdir()
    case = LIVE_SIGNAL_CASES[name](work, base, live_db3)
    case.name = name
    before = folder_state(work, tuple(work / w for w in ("cache", "usercache", "xdg", "home", "tmpdir")) + case.writes)
    run = run_massviz(case.argv, work, when=case.when, send=case.send)
    check_promise(case, run, work, before)


def test_signal_during_a_native_import_is_an_interrupt(monkeypatch, tmp_path, capsys):
    """pybind11 modules (pyrealsense2) turn a signal raised while they initialise into ``ImportError("initialization
    failed")``: it was reported as "needs pyrealsense2" (exit 2); it is the interrupt (exit 128 + the signal)."""
    import importlib.abc

    from massviz import cli

    class Interrupted(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "pyrealsense2":
                raise ImportError("initialization failed") from cli.Terminated(signal.SIGTERM)
            return None

    monkeypatch.delitem(sys.modules, "pyrealsense2", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Interrupted(), *sys.meta_path])
    code = cli.main(["live", "--file", str(tmp_path / "x.db3"), "--save", str(tmp_path / "rec"), "--no-cache"])
    err = capsys.readouterr().err
    assert code == 128 + signal.SIGTERM and err.strip() == "massviz live: interrupted (SIGTERM)", (code, err)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_signal_while_the_arguments_are_read_is_an_interrupt(sig, monkeypatch, capsys):
    """A signal that comes while argparse reads the arguments (a "-start" live case hit it: a traceback from
    argparse): one "interrupted" line naming the command, exit 128 + the signal."""
    import argparse

    from massviz import cli

    def parse_args(self, *args, **kwargs):
        raise cli.Terminated(sig)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_args)
    code = cli.main(["--quiet", "live", "--file", "x.db3"])
    err = capsys.readouterr().err
    assert code == 128 + sig and err.strip() == f"massviz live: interrupted ({signal.Signals(sig).name})", (code, err)


@pytest.mark.parametrize("where", ["parser", "handlers-in", "handlers-out"])
def test_ctrl_c_before_or_after_the_command_is_an_interrupt(where, monkeypatch, capsys):
    """A Ctrl-C while ``main`` builds the parser or puts the SIGTERM/SIGHUP handlers in (the "-start" live case
    hit it: a traceback from ``signal.signal``, exit -2) or takes them out: one line naming the command, exit 130,
    and the handlers that were there before are back."""
    from massviz import cli

    signals = (signal.SIGINT, *cli.CLEANUP_SIGNALS)
    before = {sig: signal.getsignal(sig) for sig in signals}
    real_signal, calls = signal.signal, []

    def interrupted_signal(sig, handler):
        calls.append(sig)
        out = real_signal(sig, handler)
        # the 2nd of the three going in, or the 1st coming out; after the handler changed: the worst moment
        if (where == "handlers-in" and len(calls) == 2) or (where == "handlers-out" and len(calls) == 4):
            raise KeyboardInterrupt
        return out

    def interrupted_parser():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.signal, "signal", interrupted_signal)
    if where == "parser":
        monkeypatch.setattr(cli, "build_parser", interrupted_parser)
    else:
        monkeypatch.setattr(cli, "_run", lambda parser, argv: 0)
    try:
        code = cli.main(["--quiet", "score", "x.csv"])
    except KeyboardInterrupt:  # not pytest's own Ctrl-C: the failure this test is for
        code = "KeyboardInterrupt escaped"
    err = capsys.readouterr().err
    monkeypatch.undo()
    assert code == 130 and err == "massviz score: interrupted\n", (code, err)
    if where == "handlers-in":
        assert {sig: signal.getsignal(sig) for sig in signals} == before
    for sig, handler in before.items():
        signal.signal(sig, handler)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_an_import_waits_for_its_end(sig, monkeypatch, tmp_path):
    """While a command runs, a signal that comes in the middle of an import is raised once the import is done
    (numpy turns an exception raised inside its import into "Importing the numpy C-extensions failed", pybind11
    into "initialization failed", importlib's weakref callbacks print and drop it): the module is whole, the
    interrupt still ends the command, with its signal."""
    import importlib

    from massviz import cli

    name = f"slow_import_for_signal_{int(sig)}"
    (tmp_path / f"{name}.py").write_text(
        "import os, signal, time\n"
        f"os.kill(os.getpid(), {int(sig)})\n"
        "t = time.monotonic()\n"
        "while time.monotonic() - t < 0.3:\n"
        "    sum(range(1000))  # Python code runs: the handler is called here\n"
        "complete = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)
    seen = {}

    def command(parser, argv):
        t = time.monotonic()
        try:
            seen["imported"] = importlib.import_module(name).complete
            t = time.monotonic()
            while time.monotonic() - t < 5:
                time.sleep(0.001)
        except KeyboardInterrupt as err:
            seen["raised"] = type(err).__name__, time.monotonic() - t
            raise
        return 0

    monkeypatch.setattr(cli, "_run", command)
    try:
        code = cli.main(["score", "x.csv"])
    except KeyboardInterrupt:
        code = "escaped"
    assert seen.get("imported") is True, seen
    assert code == 128 + sig and seen["raised"][0] == ("Terminated" if sig != signal.SIGINT else "KeyboardInterrupt")
    assert seen["raised"][1] < 1.0, seen  # handed back soon after the import (10 ms polls)


def test_an_ignored_hangup_stays_ignored(monkeypatch):
    """``nohup massviz ...``: SIGHUP is ignored when massviz starts; it stays ignored while the command runs."""
    from massviz import cli

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        during = {}
        monkeypatch.setattr(cli, "_run", lambda parser, argv: during.setdefault("hup", signal.getsignal(signal.SIGHUP))
                            and 0)
        assert cli.main(["score", "x.csv"]) == 0
        assert during["hup"] == signal.SIG_IGN and signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_ctrl_c_while_the_command_line_is_imported_is_an_interrupt(monkeypatch, capsys):
    """``python -m massviz`` and the ``massviz`` script (both ``massviz.__main__.run``): a Ctrl-C while
    ``massviz.cli`` itself is imported is one line and exit 130, not a traceback."""
    import importlib.abc

    from massviz.__main__ import run

    class Interrupted(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "massviz.cli":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "massviz.cli")
    monkeypatch.setattr(sys, "meta_path", [Interrupted(), *sys.meta_path])
    try:
        code = run()
    except KeyboardInterrupt:
        code = "KeyboardInterrupt escaped"
    assert (code, capsys.readouterr().err) == (130, "massviz: interrupted\n")


# ============================================================================================= the library, too
def _library_calls(work: Path, b: Base):
    """(what, callable) on the same hostile fixtures through the API."""
    import massviz as mv
    from massviz.evaluation.failures import load_exclusions
    from massviz.evaluation.metrics import parse_class_map, read_predictions
    from massviz.io.ccm_annotations import read_annotations
    from massviz.io.checkpoint import load_checkpoint
    from massviz.io.trace_file import load_trace

    calls = []
    for p in ("int5000", "deep100k-list", "deep100k-object"):
        for target in ("meta", "intrinsics"):
            (work / f"{target}-{p}").mkdir()
            case = json_case(target, p)(work / f"{target}-{p}", b)
            calls.append((f"open_recording {target} {p}",
                          lambda c=case: [None for _ in mv.open_recording(c.culprit.parent).frames()]))
        path = work / f"x-{p}.json"
        path.write_text(JSON_PAYLOADS[p])
        calls += [(f"parse_class_map {p}", lambda q=path: parse_class_map(str(q))),
                  (f"load_exclusions {p}", lambda q=path: load_exclusions(q))]
    for name in CHECKPOINTS:
        (work / f"ck-{name}").mkdir()
        checkpoint = _ckpt(CHECKPOINTS[name][0])(work / f"ck-{name}", b)
        calls.append((f"load_checkpoint {name}", lambda c=checkpoint: load_checkpoint(c)))
    for name in ("300MB",):
        bomb = npz_bomb(work / f"bomb-{name}.npz", BOMBS[name][0])
        calls.append((f"load_trace bomb {name}", lambda q=bomb: load_trace(q)))
    for edit in TRACE_EDITS:
        (work / f"tr-{edit}").mkdir()
        case = trace_case(edit, "compare")(work / f"tr-{edit}", b)
        calls.append((f"load_trace {edit}", lambda q=case.culprit: load_trace(q)))
    for name in ("tiny-mass-5e-324", "dup-column-ann", "dup-column-pred", "huge-pred-1e300"):
        (work / f"tb-{name}").mkdir()
        case = table_case(name)(work / f"tb-{name}", b)
        reader = read_annotations if case.culprit.name == "ann.csv" else read_predictions
        calls.append((f"{reader.__name__} {name}", lambda r=reader, q=case.culprit: r(q)))
    return calls


def test_the_library_raises_only_massviz_errors(base, tmp_path):
    from massviz.errors import MassvizError

    calls = _library_calls(tmp_path, base)
    assert len(calls) >= 30
    for what, call in calls:
        try:
            call()
        except MassvizError as err:
            assert err.path is not None or "mapping" in str(err), (what, err)
            assert "\n" not in str(err), (what, err)
        except BaseException as err:  # noqa: BLE001 - the point of the test
            raise AssertionError(f"{what}: raised {type(err).__name__}: {err}"[:400]) from None
        else:
            raise AssertionError(f"{what}: accepted")
