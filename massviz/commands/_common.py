"""Options shared by the commands that run the pipeline, and the objects they build."""
from __future__ import annotations

import argparse
import math

from massviz.core.types import PRECISIONS

PIPELINE_HELP = """
detectors (--detector):
  auto      maskrcnn when its weights are given or cached, else nanodet when its model is given or cached, else
            depth; never touches the network, always says which it chose and why (default)
  maskrcnn  paper fidelity: the paper's torchvision Mask R-CNN (cup, book, wine glass, bottle; score > threshold);
            ~3-4 s a 1280x720 frame on a 2-core CPU
  nanodet   CPU / live / offline: OpenCV Zoo's NanoDet through cv2.dnn (the same classes, cut 0.3; 3.8 MB
            model, downloaded once, sha256-pinned); ~0.1 s a frame. Boxes only: the mask is the surface grown
            from the box's centre over continuous depth, the table it stands on left out, so d is that
            surface's mean depth (the paper's d averages Mask R-CNN's silhouette)
  depth     no weights at all: the nearest free-standing object(s) in the depth map (no class; objects cut by the
            image border are not candidates); works offline
  replay    detections saved earlier (--replay trace.npz or a detections JSON file)

mass-CNN weights: --weights PATH, else $MASSVIZ_WEIGHTS, else the paper's published checkpoint is downloaded once
(sha256-checked) into the user cache. Traces are cached (--cache DIR, $MASSVIZ_CACHE_DIR or the user cache) so a
new K, a higher threshold or another model reuses the detections without running the detector again.
"""


def add_dataset_args(p: argparse.ArgumentParser, metavar: str = "REC") -> None:
    """Positional recordings / dataset roots (-> ``args.recordings``) and ``--view`` for CCM roots; expand them with
    ``massviz.commands.estimate.collect_recordings(args.recordings, args.view)``."""
    p.add_argument("recordings", nargs="+", metavar=metavar,
                   help="recording folders, CCM videos (ROOT/viewN/rgb/NNNNNN.mp4), RealSense files (.db3, .bag), CCM "
                   "dataset roots or folders of recordings")
    p.add_argument("--view", type=int, default=3, choices=[1, 2, 3, 4],
                   help="camera view of a CCM dataset root (default: 3, the paper's fixed frontal view)")


def add_pipeline_args(p: argparse.ArgumentParser, selection: bool = True) -> None:
    """The pipeline options; ``selection=False`` leaves --threshold and --k to the command (e.g. sweeps)."""
    g = p.add_argument_group("pipeline")
    g.add_argument("--detector", default="auto", choices=["auto", "maskrcnn", "nanodet", "depth", "replay"],
                   help="which detector finds the containers (default: auto; see 'detectors' below)")
    if selection:
        g.add_argument("--threshold", type=float, default=None, metavar="T",
                       help="keep detections with score > T (default: the detector's own cut: 0.4 for maskrcnn, the "
                       "paper's; 0.3 for nanodet; 0.4 for depth; a replayed trace's own; docs/detectors.md)")
        g.add_argument("--k", type=int, default=5, metavar="K",
                       help="average the predictions of the K nearest detections (default: 5, the paper's)")
    g.add_argument("--stride", type=int, default=1, metavar="N", help="process every N-th frame (default: 1)")
    g.add_argument("--weights", metavar="PATH",
                   help="mass-CNN checkpoint (default: $MASSVIZ_WEIGHTS or the published one, downloaded once)")
    g.add_argument("--detector-weights", metavar="PATH",
                   help="offline copy of the detector's weights: torchvision's Mask R-CNN COCO state_dict, or "
                   "(.onnx) OpenCV Zoo's object_detection_nanodet_2022nov.onnx for nanodet")
    g.add_argument("--replay", metavar="PATH", help="with --detector replay: a saved trace (.npz) or detections JSON")
    g.add_argument("--device", default="auto", metavar="DEV",
                   help="where the pipeline computes: auto (a CUDA GPU when there is one, else the CPU; default), "
                   "cpu, cuda or cuda:N. On CUDA, Mask R-CNN, the masks, d, the patches and the mass CNN all run on "
                   "the GPU (the depth and NanoDet detectors stay on the CPU); recorded in the trace")
    g.add_argument("--batch", type=int, metavar="N",
                   help="frames per detector forward (Mask R-CNN, NanoDet), their patches predicted by the mass CNN "
                   "together. Default: 1, except 8 for Mask R-CNN in bf16/fp16 on CUDA. A batch of N frames may "
                   "round differently from N batches of 1 (float rounding; docs/gpu.md)")
    g.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="Mask R-CNN arithmetic: fp32 (default, the paper's: IEEE fp32, no TF32, deterministic "
                   "kernels on CUDA), bf16 (CPUs with bfloat16 support, CUDA; the mass CNN runs in bf16 too) or "
                   "fp16 (CUDA; the mass CNN stays fp32). Reduced precision is faster but changes results: measure "
                   "how much with 'massviz compare'. Recorded in the trace and its cache key")
    g.add_argument("--cache", metavar="DIR", help="trace cache directory (default: $MASSVIZ_CACHE_DIR or user cache)")
    g.add_argument("--no-cache", action="store_true", help="neither read nor write the trace cache")
    g.add_argument("--quiet", action="store_true",
                   help="no progress bars (warnings, fallbacks and auto's detector choice are still printed)")
    g.add_argument("--allow-partial", action="store_true",
                   help="process a video cut short (fewer frames decode than its header declares) as far as it "
                   "decodes, with a warning on stderr and in Rerun's /log (default: that is an error)")


def build(args, threshold: float | None = None):
    """The pipeline (``massviz.app.Pipeline``: detector, model, cache) from parsed args (``threshold``
    overrides ``args.threshold``)."""
    from massviz.app import PipelineOptions, build_pipeline

    overrides = {} if threshold is None else {"threshold": threshold}
    return build_pipeline(PipelineOptions.from_args(args, **overrides))


def flag_warning(command: str, trace) -> str | None:
    """The one line a command prints (stderr) for a recording whose chosen patches are flagged (``trace.flags``),
    e.g. "massviz log: warning: cup_handover: 3 of 5 chosen patches look like another object (frames 8–10, track 1):
    without them 8.3 g [ground truth: the pitcher]"; for a recording not estimated, why ("not estimated: only
    border-cut / implausibly sized objects: ..."); None when nothing is flagged and it was estimated."""
    line = trace.flags.warning()
    if line is None and trace.estimate < 0:  # not estimated: say why (e.g. only border-cut objects were seen)
        from massviz.core.selection import why_not_estimated

        line = why_not_estimated(trace.detections, trace.events).warning()
    return None if line is None else f"massviz {command}: warning: {trace.recording.id}: {line}"


def unmatched_line(command: str, trace, unmatched) -> str:
    """The line for exclusion entries of a recording that match none of its detections."""
    return (f"massviz {command}: {trace.recording.id}: {len(unmatched)} exclusion(s) match no detection "
            f"(first: frame {unmatched[0].frame}, box {list(unmatched[0].box)})")


# -------------------------------------------------------------------------------------------- float option bounds
#: (lo, hi, lo_open, hi_open) of the float options that have their own bounds; every other float option: finite and
#: within ±MAX_FLOAT_OPTION.
FLOAT_OPTION_BOUNDS = {"iou": (0.0, 1.0, True, False), "lr": (0.0, 1e3, True, False),
                       "duration": (0.0, 1e9, True, False), "pitch": (-90.0, 90.0, True, True)}
#: float options that are a value of the selection, checked by ``Selection.check`` (the name it knows them by)
SELECTION_FLOAT_OPTIONS = {"threshold": "threshold", "b_threshold": "threshold"}
#: largest magnitude of any other float option (degrees, seconds: all far below).
MAX_FLOAT_OPTION = 1e9


def check_float_options(args: argparse.Namespace) -> None:
    """Every float option of a parsed command line finite and within its bounds (:data:`FLOAT_OPTION_BOUNDS`, else
    ±:data:`MAX_FLOAT_OPTION`), checked by ``massviz.io.untrusted.number`` as the numbers in files are: ``nan``,
    ``inf`` or ``--iou 0`` is one ``MassvizError`` naming the option, before any work; ``-0`` becomes 0.0."""
    from massviz.core.selection import Selection
    from massviz.errors import MassvizError
    from massviz.io.untrusted import number

    for dest, value in vars(args).items():
        if not isinstance(value, float):
            continue
        option = f"--{dest.replace('_', '-')}"
        if dest in SELECTION_FLOAT_OPTIONS:  # the selection's one rule and words; a non-finite value said as such
            if not math.isfinite(value):
                number(value, option, lo=0.0, hi=1.0, hi_open=True, error=MassvizError)  # raises: not finite
            try:
                setattr(args, dest, Selection.check(SELECTION_FLOAT_OPTIONS[dest], value, option) + 0.0)  # -0 is 0
            except ValueError as err:
                raise MassvizError(str(err)) from None
            continue
        lo, hi, lo_open, hi_open = FLOAT_OPTION_BOUNDS.get(dest, (-MAX_FLOAT_OPTION, MAX_FLOAT_OPTION, False, False))
        setattr(args, dest, number(value, option, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, error=MassvizError))


# ------------------------------------------------------------------------------------------ integer option bounds
#: bounds of the integer options that have their own (every other integer option: at most MAX_INT_OPTION in size).
INT_OPTION_BOUNDS = {"threads": (1, 1024), "workers": (1, 1024), "seed": (0, 2**32 - 1)}
#: largest magnitude of any integer option (a frame index, K, a batch, a port: all far below).
MAX_INT_OPTION = 2**31 - 1


def check_int_options(args: argparse.Namespace) -> None:
    """Every integer option of a parsed command line within its bounds (:data:`INT_OPTION_BOUNDS`, else
    ±:data:`MAX_INT_OPTION`): ``--threads 2**70`` or ``--seed -1`` is one clear ``MassvizError`` naming the option,
    before any work (the commands check their options' meaning, e.g. ``--k >= 1``, after this)."""
    from massviz.errors import MassvizError

    for dest, value in vars(args).items():
        if isinstance(value, bool) or not isinstance(value, int):
            continue
        lo, hi = INT_OPTION_BOUNDS.get(dest, (-MAX_INT_OPTION, MAX_INT_OPTION))
        if not lo <= value <= hi:
            shown = str(value) if len(str(value)) <= 30 else f"{str(value)[:27]}..."
            raise MassvizError(f"--{dest.replace('_', '-')} {shown}: must be an integer in [{lo}, {hi}]")
