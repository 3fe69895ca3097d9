"""Detect, features and predict for a batch of frames: the per-frame work before the selection, on the CPU or a
CUDA GPU. ``FramePipeline.step`` takes what this computes; ``run`` streams a recording through it.

Two sets of kernels compute the same three stages (``FrameStage(kernels=...)``):

* ``exact`` (the CPU's default): the detector's ``detect``/``detect_batch`` (host ``Detections`` with masks), d, a
  and b with numpy (``compute_features``), each patch cropped on the host and resized by Pillow for the mass CNN
  (``MassPredictor.predict_groups``): bit for bit the paper's CPU arithmetic. Nothing else is ever run on a CPU by
  default.
* ``device`` (CUDA's default): the frames are copied to the device once (from pinned memory, without blocking);
  Mask R-CNN's masks stay there and are pasted only inside their boxes (the detector's ``detect_device``), d is
  summed there; every patch is cut, zero-padded and resized there (``massviz.core.resample``, Pillow's bytes exactly)
  and the mass CNN runs there in calls of a fixed size (``MassPredictor.predict_normalised``). Back to the host come only
  the boxes, scores and classes (one copy, after the detector), then d, the masks' bits inside their boxes
  (``np.packbits``' layout, packed on the device: ``massviz.core.windows.window_features``, one function for the
  windows, d and the bits) and the predictions (one copy at the end of the batch, into pinned memory on CUDA). A
  detector without ``detect_device`` (depth, NanoDet, replay) detects on the host; its masks' d is computed there
  and the patches still go to the device. With ``detect_ahead`` (CUDA's default) the detector of the next batch
  runs in a thread (and on CUDA a stream) of its own while this batch is post-processed
  (``massviz.core.streams``: on a CPU the same code with no streams).

The two agree up to float rounding on the same device (tests/test_device_path.py runs both on the CPU); on the CPU
the default stays ``exact``. Stage times: a batch's detect, features and predict seconds are shared equally by its
frames. On CUDA the device works asynchronously: its time is charged to the stage that waits for it (predict, whose
end copies the results).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from massviz.core.features import box_ratios, compute_features
from massviz.core.patches import crop
from massviz.core.types import Detections, Frame, PackedMask
from massviz.core.windows import packed_bytes

KERNELS = ("auto", "exact", "device")
#: most mask-window pixels (detections x height x width) gathered at once on the device
WINDOW_BUDGET = 1 << 25


class FramePatches:
    """Each detection's RGB patch (``massviz.core.patches.crop`` of its box), cut when read."""

    def __init__(self, rgb: np.ndarray, xyxy: np.ndarray):
        self._rgb, self._xyxy = rgb, np.asarray(xyxy).reshape(-1, 4)

    def __len__(self) -> int:
        return len(self._xyxy)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return crop(self._rgb, self._xyxy[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))


@dataclass
class StagedFrame:
    """One frame after detect, features and predict: its detections with d, a, b and ``pred``, their patches
    (``FramePatches``), this frame's seconds per stage and the detector's notes (e.g. the depth detector's rejected
    objects)."""

    frame: Frame
    detections: Detections
    patches: FramePatches
    timings: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)


def model_device(model):
    """The torch device of a model (``MassPredictor.device``), else of its parameters (the CPU for a model without
    any, e.g. a test's stand-in)."""
    import torch

    if isinstance(getattr(model, "device", None), torch.device):
        return model.device
    params = getattr(model, "parameters", None)
    if params is None:
        return torch.device("cpu")
    try:
        return next(params()).device
    except (StopIteration, TypeError):
        return torch.device("cpu")


def same_device(a, b) -> bool:
    """Whether two torch devices are the same (``cuda`` without an index is the current CUDA device)."""
    import torch

    a, b = torch.device(a), torch.device(b)
    if a.type != b.type:
        return False
    if a.type != "cuda":
        return True
    current = torch.cuda.current_device()
    return (current if a.index is None else a.index) == (current if b.index is None else b.index)


def run_precision(detector, model) -> str:
    """A run's ``--precision``: the detector's (Mask R-CNN's), else the mass CNN's, else ``fp32``."""
    return getattr(detector, "precision", None) or getattr(model, "precision", "fp32")


def _check_finite(model, pred: np.ndarray) -> None:
    if not np.isfinite(pred).all():  # weights whose numbers are finite but overflow on this input
        from massviz.errors import WeightsError

        raise WeightsError("the mass CNN predicted a non-finite mass (its weights or ranges overflow)",
                           getattr(model, "checkpoint_path", None))


def predictable(dets: Detections) -> np.ndarray:
    """Indices of the detections the mass CNN predicts: a finite d and a non-empty box."""
    wide = (dets.xyxy[:, 2] > dets.xyxy[:, 0]) & (dets.xyxy[:, 3] > dets.xyxy[:, 1])
    return np.flatnonzero(np.isfinite(dets.d) & wide)


class FrameStage:
    """Detect, features and predict for batches of frames (module docstring). ``device``: where the mass CNN runs
    (default: the device of its parameters); ``kernels``: ``auto`` (``device`` on CUDA, ``exact`` elsewhere),
    ``exact`` or ``device``; ``batch``: frames per detector call (``stream``)."""

    def __init__(self, detector, model, *, batch: int = 1, kernels: str = "auto", overlap: bool | None = None,
                 detect_ahead: bool | None = None):
        if kernels not in KERNELS:
            raise ValueError(f"kernels must be one of {', '.join(KERNELS)}, got {kernels!r}")
        if batch < 1:
            raise ValueError("batch must be >= 1")
        self.detector, self.model, self.batch = detector, model, int(batch)
        self.device = model_device(model)
        has_net = hasattr(model, "predict_normalised") and getattr(model, "ranges", None) is not None
        if kernels == "auto":
            kernels = "device" if self.device.type == "cuda" and has_net else "exact"
        if kernels == "device" and not has_net:
            raise ValueError("the device kernels need the mass CNN (a MassPredictor with its ranges)")
        self.kernels = kernels
        self._overlap = overlap
        self._detect_ahead = detect_ahead

    @property
    def precision(self) -> str:
        """The run's ``--precision``: the detector's, else the mass CNN's (``fp32`` for models without one)."""
        return str(run_precision(self.detector, self.model))

    def faithful(self):
        """The faithful settings of this stage's run (``massviz.core.device.faithful_fp32`` on its device, in
        fp32): entered once around a run (``massviz.core.pipeline.run``) and around each batch (then only
        counted)."""
        from massviz.core.device import faithful_fp32

        return faithful_fp32(self.device, self.precision == "fp32")

    def describe(self) -> dict:
        """What a trace records of where it was computed: device, kernels, precision, batch and the mode
        (``faithful``: fp32, the paper's arithmetic, computed in :meth:`faithful`'s settings; ``fast``:
        bf16/fp16)."""
        from massviz.core.device import describe

        precision = self.precision
        return {"device": describe(self.device), "kernels": self.kernels, "precision": precision,
                "batch": self.batch, "mode": "faithful" if precision == "fp32" else "fast"}

    @property
    def overlap(self) -> bool:
        """Whether ``run`` computes the next batches in a thread of their own while the caller selects (default:
        on CUDA)."""
        return self.device.type == "cuda" if self._overlap is None else bool(self._overlap)

    @property
    def detect_ahead(self) -> bool:
        """Whether the device kernels run the detector of the next batch while this one is post-processed (a thread
        of its own, on CUDA a stream of its own; default: on CUDA). The results are the same either way."""
        return self.device.type == "cuda" if self._detect_ahead is None else bool(self._detect_ahead)

    @property
    def read_workers(self) -> int:
        """Threads that decode a recording's depth images for this stage: several on CUDA (a GPU consumes frames
        faster than one thread decodes them), 1 on the CPU (its cores run the detector)."""
        import os

        return min(4, os.cpu_count() or 1) if self.overlap else 1

    def prepare(self, frame: Frame) -> Frame:
        """Done to each frame in the reading thread: pinned memory for a GPU's copies."""
        if self.device.type == "cuda":
            from massviz.core.device import pin_frame

            return pin_frame(frame)
        return frame

    def stream(self, frames):
        """``StagedFrame`` for each frame of the iterable ``frames``, ``batch`` frames per call of ``process``
        (with ``detect_ahead``: the detector one batch ahead of the post-processing, in a thread of its own);
        ``read`` time is the time spent waiting for each frame."""
        if self.kernels == "device" and self.detect_ahead:
            yield from self._stream_ahead(self._groups(frames))
            return
        for group, waits in self._groups(frames):
            yield from self.process(group, waits)

    def _groups(self, frames):
        """(``batch`` frames, the seconds waited for each) from the iterable ``frames``."""
        it = iter(frames)
        while True:
            group, waits = [], []
            t0 = time.perf_counter()
            for frame in it:
                t1 = time.perf_counter()
                group.append(frame)
                waits.append(t1 - t0)
                if len(group) == self.batch:
                    break
                t0 = time.perf_counter()
            if not group:
                return
            yield group, waits

    def process(self, frames: list[Frame], reads=None) -> list[StagedFrame]:
        """Detect, features and predict on ``frames`` (one detector call for all of them when the detector has
        ``detect_batch`` and there are several); ``reads``: each frame's read seconds."""
        reads = list(reads) if reads is not None else [0.0] * len(frames)
        with self.faithful():
            out = self._process_device(frames) if self.kernels == "device" else self._process_exact(frames)
        return self._with_reads(out, reads)

    # ----------------------------------------------------------------------------------------------- exact kernels
    def _detect(self, frames: list[Frame]) -> list[Detections]:
        detect_batch = getattr(self.detector, "detect_batch", None) if len(frames) > 1 else None
        return detect_batch(frames) if detect_batch is not None else [self.detector.detect(f) for f in frames]

    def _notes(self, frame: Frame) -> list:
        pop_notes = getattr(self.detector, "pop_notes", None)  # e.g. the depth detector's rejected objects
        return list(pop_notes(frame.index)) if pop_notes is not None else []

    def _process_exact(self, frames: list[Frame]) -> list[StagedFrame]:
        n = len(frames)
        t0 = time.perf_counter()
        raw = self._detect(frames)
        t1 = time.perf_counter()
        dets = [compute_features(r, f.depth) for r, f in zip(raw, frames)]  # new arrays: the detector's stay
        t2 = time.perf_counter()
        patches = [FramePatches(f.rgb, d.xyxy) for f, d in zip(frames, dets)]
        rows = [predictable(d) for d in dets]
        groups = [([p[i] for i in ok], np.stack([d.a[ok], d.b[ok], d.d[ok]], axis=1)) for p, d, ok
                  in zip(patches, dets, rows) if len(ok)]
        if len(groups) > 1 and hasattr(self.model, "predict_groups"):
            preds = iter(self.model.predict_groups(groups))
        else:  # one frame (or a model with only predict): one call per frame, as the paper's code
            preds = iter([self.model.predict(p, f) for p, f in groups])
        for d, ok in zip(dets, rows):
            d.pred = np.full(len(d), np.nan, dtype=np.float32)
            if len(ok):
                d.pred[ok] = next(preds)
                _check_finite(self.model, d.pred[ok])
        t3 = time.perf_counter()
        share = {"detect": (t1 - t0) / n, "features": (t2 - t1) / n, "predict": (t3 - t2) / n}
        return [StagedFrame(f, d, p, dict(share), self._notes(f)) for f, d, p in zip(frames, dets, patches)]

    # ---------------------------------------------------------------------------------------------- device kernels
    def _stream_ahead(self, groups):
        """``StagedFrame`` of each (frames, reads) group, the detector of group n + 1 running in a thread of its own
        (on CUDA: on a stream of its own) while group n is post-processed in this one: the same results as
        ``process`` group by group (tests/test_device_path.py)."""
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="massviz-detect")
        pending = None
        try:
            for group, reads in groups:
                ahead = (pool.submit(self._detect_device, group, True), reads)
                if pending is not None:
                    yield from self._with_reads(self._finish_device(pending[0].result()), pending[1])
                pending = ahead
            if pending is not None:
                yield from self._with_reads(self._finish_device(pending[0].result()), pending[1])
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    @staticmethod
    def _with_reads(out: list[StagedFrame], reads) -> list[StagedFrame]:
        for staged, r in zip(out, reads):
            staged.timings = {"read": r, **staged.timings}
        return out

    def _process_device(self, frames: list[Frame]) -> list[StagedFrame]:
        return self._finish_device(self._detect_device(frames, False))

    def _detect_device(self, frames: list[Frame], own_lane: bool) -> "_Detected":
        """The frames to the device and the detector on them (``own_lane``: on a stream of this thread's own, whose
        end the post-processing waits for)."""
        import torch

        from massviz.core.device import upload
        from massviz.core.streams import Lane

        dev = self.device
        if own_lane:  # one stream for the detector thread, made in it once
            lane = self._detect_lane = getattr(self, "_detect_lane", None) or Lane(dev)
        else:
            lane = Lane(dev, current=True)
        with torch.inference_mode(), self.faithful(), lane:  # counted: a thread of the run's
            t0 = time.perf_counter()
            rgb = upload([f.rgb for f in frames], dev)
            detect_device = getattr(self.detector, "detect_device", None)
            if detect_device is not None and not same_device(getattr(self.detector, "device", "cpu"), dev):
                detect_device = None  # a detector elsewhere: its own detect, host masks
            if detect_device is not None:
                raw, masks = detect_device(frames, rgb)
                depth = upload([f.depth.view(np.int16) for f in frames], dev)
            else:
                raw, masks, depth = self._detect(frames), None, None
            event = lane.record()
            t1 = time.perf_counter()
        return _Detected(frames, raw, masks, rgb, depth, event, t1 - t0)

    def _finish_device(self, det: "_Detected") -> list[StagedFrame]:
        """d, the mask bits, the patches and the mass CNN on the device for what ``_detect_device`` found; one copy
        back (into pinned memory on CUDA)."""
        import torch

        from massviz.core.resample import resize_boxes
        from massviz.core.streams import Lane, to_host

        frames, raw, masks = det.frames, det.raw, det.masks
        n, dev = len(frames), self.device
        lane = Lane(dev, current=True)
        lane.wait(det.event)
        lane.keep(det.rgb, det.depth, *((masks.padded, masks.expanded) if masks is not None else ()))
        with torch.inference_mode(), self.faithful():
            t1 = time.perf_counter()
            counts = [len(r) for r in raw]
            xyxy = np.concatenate([r.xyxy for r in raw]) if raw else np.zeros((0, 4), np.int32)
            frame_of = np.repeat(np.arange(n), counts)
            height, width = frames[0].depth.shape[:2]
            a, b = box_ratios(xyxy, width, height)
            host_d = None
            if masks is None:  # host masks: d on the host, exactly compute_features
                dets = [compute_features(r, f.depth) for r, f in zip(raw, frames)]
                host_d = np.concatenate([d.d for d in dets]) if dets else np.zeros(0)
                d_dev, chunks = torch.from_numpy(host_d).to(dev), []
            else:
                d_dev, chunks = self._distances(masks, det.depth, frame_of, xyxy)
            t2 = time.perf_counter()
            wide = np.flatnonzero((xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1]))
            images = resize_boxes(det.rgb, frame_of[wide], xyxy[wide])
            feats = torch.stack([torch.from_numpy(a[wide]).to(dev), torch.from_numpy(b[wide]).to(dev),
                                 torch.nan_to_num(d_dev[torch.from_numpy(wide).to(dev)], nan=0.0)], dim=1)
            y = self.model.predict_normalised(images, self.model.ranges.normalise_features_tensor(feats))
            # the one copy back: predictions, d, and the masks' bits
            y, d, *bits = to_host([y, None if host_d is not None else d_dev, *(c[1] for c in chunks)])
            d = host_d if host_d is not None else d
            t3 = time.perf_counter()
        pred = np.full(len(xyxy), np.nan, dtype=np.float32)
        ok = np.isfinite(d[wide])
        pred[wide[ok]] = self.model.ranges.denormalise_mass(y[ok])
        _check_finite(self.model, pred[wide[ok]])
        mask_list = [None] * len(xyxy)
        h, w = np.maximum(xyxy[:, 3] - xyxy[:, 1], 0), np.maximum(xyxy[:, 2] - xyxy[:, 0], 0)
        nbytes = packed_bytes(h, w)
        for (idx, _), packed in zip(chunks, bits):
            for row, i in enumerate(idx):
                mask_list[i] = PackedMask(shape=(int(h[i]), int(w[i])), bits=packed[row, :nbytes[i]].copy())
        out, start = [], 0
        share = {"detect": det.seconds / n, "features": (t2 - t1) / n, "predict": (t3 - t2) / n}
        for f, r, c in zip(frames, raw, counts):
            sl = slice(start, start + c)
            masks_f = mask_list[sl] if masks is not None else list(r.masks)
            dets_f = Detections(frame=r.frame, xyxy=r.xyxy, score=r.score, class_id=r.class_id, masks=masks_f,
                                d=d[sl], a=a[sl], b=b[sl], pred=pred[sl])
            out.append(StagedFrame(f, dets_f, FramePatches(f.rgb, dets_f.xyxy), dict(share), self._notes(f)))
            start += c
        return out

    def _distances(self, masks, depth, frame_of: np.ndarray, xyxy: np.ndarray):
        """d of every detection on the device (float64, NaN without depth) and the masks' bits in ``np.packbits``
        layout, in chunks of similar size: (d, [(detection indices, (k, nbytes) uint8 tensor)]), each chunk one call
        of ``massviz.core.windows.window_features`` (compiled on CUDA; its sizes and count bucketed)."""
        import torch

        from massviz.core.streams import bucket, compiled
        from massviz.core.windows import window_features

        dev = depth.device
        h = np.maximum(xyxy[:, 3] - xyxy[:, 1], 0)
        w = np.maximum(xyxy[:, 2] - xyxy[:, 0], 0)
        d = torch.full((len(xyxy),), float("nan"), dtype=torch.float64, device=dev)
        chunks = []
        order = np.argsort(h * w, kind="stable")
        # one copy of the boxes (in chunk order) to the device
        geo_host = torch.from_numpy(np.concatenate([frame_of[:, None], xyxy], axis=1).astype(np.int64)[order])
        geo = (geo_host.pin_memory() if dev.type == "cuda" else geo_host).to(dev, non_blocking=dev.type == "cuda")
        order_dev = torch.from_numpy(order).to(dev)
        hundred = torch.full((), 100.0, dtype=torch.float64, device=dev)  # a tensor: a true division on CUDA
        run = compiled(window_features, dev)
        start = 0
        while start < len(order):  # chunks of similar size, each at most WINDOW_BUDGET pixels (or one detection)
            end, hh, ww = start + 1, max(int(h[order[start]]), 1), max(int(w[order[start]]), 1)
            while end < len(order):
                h2, w2 = max(hh, int(h[order[end]])), max(ww, int(w[order[end]]))
                if (end + 1 - start) * h2 * w2 > WINDOW_BUDGET:
                    break
                end, hh, ww = end + 1, h2, w2
            k = end - start
            kb, hb, wb = bucket(k, least=8), bucket(hh), bucket(ww)  # padded: the last detection repeated
            rows = torch.cat([torch.arange(start, end, device=dev), torch.full((kb - k,), end - 1, device=dev)])
            idx_dev = order_dev[rows]
            dd, bits = run(masks.padded[idx_dev], masks.expanded[idx_dev], depth, geo[rows], hundred, hb, wb,
                           (hb * wb + 7) // 8, masks.im_h, masks.im_w, masks.threshold)
            d[order_dev[start:end]] = dd[:k]
            chunks.append((order[start:end], bits[:k]))
            start = end
        return d, chunks


class _Detected:
    """What the detector part of the device path hands the post-processing: the frames, their detections (host
    boxes), the masks on the device (or None), the frames' RGB and depth there, the event ending that work and
    its seconds."""

    __slots__ = ("depth", "event", "frames", "masks", "raw", "rgb", "seconds")

    def __init__(self, frames, raw, masks, rgb, depth, event, seconds):
        self.frames, self.raw, self.masks, self.rgb = frames, raw, masks, rgb
        self.depth, self.event, self.seconds = depth, event, seconds


__all__ = ["KERNELS", "FrameStage", "StagedFrame", "FramePatches", "model_device", "predictable", "run_precision"]
