"""Two runs and the patch map at dataset scale: on the synthetic 1,140-recording cached dataset of
``benchmarks/dataset_scale.py`` (built the same way: hard-linked frame files, a cache entry per recording with a
trace file and a selection index of 2–10 detections a frame, 1.4 M detections in all),

* the two runs of every recording from the cache's selection indexes (``run_from_indexes``: K 5 at threshold 0.4
  and K 3 at 0.5: selection, estimate and flags of each) and the comparison table (``compare_runs``, including
  the patch matching by frame and box) and the scores (``run_scores``);
* the embedding of every chosen patch (``embed_traces`` over each recording's full trace file: its 5 nearest
  patches at threshold 0.4, through the mass CNN's pooled features), cold (computed and written beside the cache entries)
  and warm (read back), the 2D layout of all of them (``layout_2d``) and a similar-patch query (``nearest``);
* the map's redraw in a page (headless Chromium, when playwright and Debian's chromium are there): a plotly scatter
  of every chosen patch in the page (plotly.js from the plotly package, offline), the time from a colour change
  (``Plotly.restyle``) to the page's next frame, by ``performance.now()``.

    MASSVIZ_WEIGHTS=../shared/weights/corsmal_visual/Encoder_pool_aug_158.torch \\
        .venv/bin/python benchmarks/runs_and_patch_map.py [--n 1140] [--repeat 3] [--out DIR]

Each timing is repeated (``--repeat``) and printed as its median (and the single runs), with the machine's load
average (the machine is shared: figures move with the load).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def timed(fn, repeat: int):
    """(last result, [seconds of each run])."""
    out, times = None, []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, times


def line(what: str, times: list[float], unit: str = "s") -> str:
    scale = 1000.0 if unit == "ms" else 1.0
    runs = ", ".join(f"{scale * t:.{0 if unit == 'ms' else 2}f}" for t in times)
    return (f"| {what} | {scale * statistics.median(times):.{0 if unit == 'ms' else 2}f} {unit} | {runs} | "
            f"{load()} |")


def page_redraw(xy: np.ndarray, repeat: int) -> list[float] | None:
    """Milliseconds from ``Plotly.restyle`` (a colour change of every point) to the page's next animation frame,
    in headless Chromium; None without playwright or chromium."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    chromium = Path(os.environ.get("MASSVIZ_CHROMIUM", "/usr/bin/chromium"))
    if not chromium.is_file():
        return None
    import plotly

    js = Path(plotly.__file__).parent / "package_data" / "plotly.min.js"
    with tempfile.TemporaryDirectory() as tmp:
        page_file = Path(tmp) / "map.html"
        shutil.copy(js, Path(tmp) / "plotly.min.js")
        page_file.write_text(
            "<html><body><div id='map' style='width:720px;height:480px'></div><script src='plotly.min.js'></script>"
            f"<script>const xy = {json.dumps(np.round(xy, 3).tolist())};"
            "Plotly.newPlot('map', [{type: xy.length > 2000 ? 'scattergl' : 'scatter', mode: 'markers',"
            "x: xy.map(p => p[0]), y: xy.map(p => p[1]), marker: {size: 6, color: xy.map(p => p[0])}}],"
            "{dragmode: 'select'});</script></body></html>")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(chromium), headless=True,
                                        args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page()
            page.goto(page_file.as_uri())
            page.wait_for_function("() => document.querySelector('#map .main-svg') !== null", timeout=60_000)
            out = []
            for i in range(repeat):
                out.append(page.evaluate("""(i) => new Promise(done => {
                    const n = document.getElementById('map').data[0].x.length;
                    const colours = Array.from({length: n}, (_, j) => ((j * 7 + i) % 10));
                    const t0 = performance.now();
                    Plotly.restyle('map', {'marker.color': [colours]}).then(() =>
                        requestAnimationFrame(() => done(performance.now() - t0)));
                })""", i))
            browser.close()
    return [v / 1000.0 for v in out]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1140, help="recordings (default: 1140)")
    p.add_argument("--repeat", type=int, default=3, help="runs of each timing (default: 3)")
    p.add_argument("--out", help="work folder (default: a temporary one, removed at the end)")
    args = p.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    reference = ROOT.parent / "shared" / "weights" / "corsmal_visual" / "Encoder_pool_aug_158.torch"
    env.setdefault("MASSVIZ_WEIGHTS", str(reference))
    os.environ.setdefault("MASSVIZ_WEIGHTS", env["MASSVIZ_WEIGHTS"])
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
          f"{platform.python_version()}; load average {load()}")
    tmp = None if args.out else tempfile.mkdtemp(prefix="massviz-runs-")
    work = Path(args.out or tmp)
    try:
        from types import SimpleNamespace

        from dataset_scale import build

        from massviz.commands._warm import cached_indexes, locate_all, warm_pipeline
        from massviz.evaluation.patch_map import PatchMap, embed_traces, layout_2d
        from massviz.evaluation.runs import compare_runs, run_from_indexes, run_scores
        from massviz.io.recording import find_recordings
        from massviz.io.trace_file import load_trace

        cache, out = work / "cache", work / "dataset" / "all"
        build(out, cache, args.n, env)
        cli = SimpleNamespace(cache=str(cache), no_cache=False, detector="depth", weights=env["MASSVIZ_WEIGHTS"],
                              detector_weights=None, replay=None, precision="fp32", threshold=0.4, k=5, stride=1)
        pipeline = warm_pipeline(cli, 0.4)
        t0 = time.perf_counter()
        indexes = cached_indexes(pipeline, locate_all(find_recordings(out), cache), 1, 0.4)
        print(f"read {len(indexes)} selection indexes in {time.perf_counter() - t0:.2f} s")
        print(f"\n{len(indexes)} recordings, {args.repeat} runs each: median | each run | load average")
        print("| step | median | runs | load |\n|---|---|---|---|")
        (run_a, run_b), times = timed(lambda: (run_from_indexes(indexes, k=5, threshold=0.4, label="K 5"),
                                               run_from_indexes(indexes, k=3, threshold=0.5, label="K 3 t0.5")),
                                      args.repeat)
        print(line("two runs from the indexes (selection, estimate, flags of each)", times), flush=True)
        table, times = timed(lambda: compare_runs(run_a, run_b), args.repeat)
        print(line(f"comparison table ({len(table)} rows, patches matched by frame and box)", times), flush=True)
        _, times = timed(lambda: run_scores(table), args.repeat)
        print(line("per-class scores of A, B and the pairwise best", times, "ms"), flush=True)

        files = [Path(i.trace_path) for i in indexes]
        from massviz.io.checkpoint import load_checkpoint
        from massviz.io.weights import resolve_weights

        model = load_checkpoint(resolve_weights(env["MASSVIZ_WEIGHTS"]))  # (the warm pipeline's model is a name)
        traces, times = timed(lambda: [load_trace(f) for f in files], 1)
        print(line(f"read {len(files)} full trace files (the patches' images)", times), flush=True)

        def embed_all():
            return embed_traces(traces, model, trace_paths=files,
                                detections=[t.reselect(k=5).selection for t in traces])

        cold, times = timed(embed_all, 1)
        n_patches = sum(len(e) for e in cold)
        print(line(f"embed every chosen patch, cold ({n_patches} patches, written beside the cache entries)",
                   times), flush=True)
        warm, times = timed(embed_all, args.repeat)
        print(line("the same, warm (read from the cache)", times), flush=True)
        features = np.stack([f for e in warm for f in e.values()])
        for method in ("pca", "auto"):
            (xy, used), times = timed(lambda method=method: layout_2d(features, method), 1)
            print(line(f"2D layout of {len(features)} patches: {used}", times), flush=True)
        import pandas as pd

        pmap = PatchMap(pd.DataFrame({"patch_id": [f"p{i}" for i in range(len(features))]}), features)
        _, times = timed(lambda: pmap.nearest("p0", 10), args.repeat)
        print(line("similar patches: nearest 10 of one", times, "ms"), flush=True)
        redraw = page_redraw(xy, max(5, args.repeat))
        if redraw is None:
            print("| map redraw in a page | (no playwright or chromium) | | |")
        else:
            print(line(f"map redraw in the page after a colour change ({len(xy)} points, headless Chromium)",
                       redraw, "ms"), flush=True)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
