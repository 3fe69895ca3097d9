"""A trace is plain data: the stages that make or change a selection (the pipeline's finish, ``reselect``,
``analyse_trace``) compute its flags, once; building it, ``dataclasses.replace`` and reading it compute nothing. The
warnings come from structured reasons, not from the events' text."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import massviz.core.trace as trace_module
from fakes import DETECTIONS, DistanceModel, ListDetector, write_recording
from massviz.app import process
from massviz.commands._common import flag_warning
from massviz.core.pipeline import run
from massviz.core.selection import REJECTED_PREFIX, NotEstimated, Selection, why_not_estimated
from massviz.core.trace import Event, Trace, analyse_trace, frame_results
from massviz.core.types import Detections, Rejection
from massviz.errors import MassvizError
from massviz.io.recording import open_recording
from massviz.io.trace_file import load_trace, save_trace


@pytest.fixture
def analyses(monkeypatch):
    """Counts the calls of the flag analysis (``massviz.core.flags.analyse``, as the trace stages call it)."""
    calls = []
    real = trace_module.analyse

    def counted(trace, **kwargs):
        calls.append(trace)
        return real(trace, **kwargs)

    monkeypatch.setattr(trace_module, "analyse", counted)
    return calls



def made(rec) -> Trace:
    return run(rec, ListDetector(DETECTIONS), DistanceModel(), k=3, prefetch=0)


def test_building_a_trace_analyses_it_once(rec, analyses):
    trace = made(rec)
    assert len(analyses) == 1 and trace.flags is not None and trace.flags.describes(trace)
    assert (trace.detections.track > 0).all()
    # the pipeline without its analysis stage leaves the flags to the caller, who analyses once
    bare = run(rec, ListDetector(DETECTIONS), DistanceModel(), k=3, prefetch=0, analyse=False)
    assert len(analyses) == 1 and bare.flags is None
    assert analyse_trace(bare).flags == trace.flags and len(analyses) == 2


def test_process_with_the_ground_truth_step_analyses_once(rec, analyses, tmp_path):
    from massviz.io.cache import TraceCache

    trace = process(rec, ListDetector(DETECTIONS), DistanceModel(), k=3, prefetch=0)
    assert len(analyses) == 1 and trace.flags.describes(trace)
    # with the cache: the run analyses once; a trace served from it is re-selected and analysed once
    cache = TraceCache(tmp_path / "cache")
    analyses.clear()
    first = process(rec, ListDetector(DETECTIONS), DistanceModel(), k=3, prefetch=0, cache=cache)
    assert len(analyses) == 1
    analyses.clear()
    detector = ListDetector(DETECTIONS)
    again = process(rec, detector, DistanceModel(), k=2, prefetch=0, cache=cache)
    assert detector.calls == 0 and any(e.kind == "cache" for e in again.events)
    assert len(analyses) == 1 and again.flags.describes(again)
    assert again.selection.tolist() == first.reselect(k=2).selection.tolist()


def test_construction_and_replace_compute_nothing(rec, analyses):
    trace = made(rec)
    analyses.clear()
    fields = {f.name: getattr(trace, f.name) for f in dataclasses.fields(trace)}
    rebuilt = Trace(**{**fields, "flags": None})
    replaced = dataclasses.replace(trace, threshold=0.5, recording=dataclasses.replace(trace.recording, path="/x"))
    untracked = Trace(**{**fields, "detections": dataclasses.replace(trace.detections,
                                                                     track=np.zeros(len(trace.detections)))})
    assert analyses == []
    assert rebuilt.flags is None and replaced.flags is trace.flags  # kept as they were, not recomputed
    assert (untracked.detections.track == 0).all()  # no tracker ran either
    # the explicit stage computes what is missing or stale, once, and nothing when the flags describe the trace
    assert analyse_trace(trace) is trace and analyses == []
    again = analyse_trace(untracked)
    assert len(analyses) == 1 and (again.detections.track == trace.detections.track).all()
    assert again.flags == trace.flags
    assert (untracked.detections.track == 0).all()  # the stage made a new trace, the old one is unchanged
    assert analyse_trace(replaced).flags.describes(replaced) and len(analyses) == 2


def test_reselect_analyses_the_new_selection_once(rec, analyses):
    trace = made(rec)
    analyses.clear()
    two = trace.reselect(k=2)
    assert len(analyses) == 1 and two.flags.describes(two) and len(two.flags.patches) == 2
    high = trace.reselect(threshold=0.6)
    assert len(analyses) == 2 and high.flags.describes(high)


def test_loading_a_trace_analyses_only_what_the_file_lacks(rec, analyses, tmp_path):
    trace = made(rec)
    analyses.clear()
    path = save_trace(trace, tmp_path / "t.npz")
    loaded = load_trace(path)
    assert analyses == [] and loaded.flags == trace.flags
    save_trace(dataclasses.replace(trace, flags=None), tmp_path / "bare.npz")
    bare = load_trace(tmp_path / "bare.npz")
    assert len(analyses) == 1 and bare.flags == trace.flags


# ----------------------------------------------------------------------------------------- structured reasons
def _unestimated(events) -> Trace:
    dets = Detections(frame=[0], xyxy=[[0, 0, 4, 4]], score=[0.2], class_id=[47], d=[800.0], pred=[5.0])
    trace = Trace(recording={"id": "r"}, detector={"name": "depth"}, detect_threshold=0.1, threshold=0.4, k=5,
                  stride=1, frames=np.arange(3), detections=dets, selection=np.zeros(0, np.int64), estimate=-1.0,
                  events=events)
    return trace.reselect()


REJECTED = [Event(0, f"{REJECTED_PREFIX}border-cut object (box [0, 1, 2, 3] at 500 mm)", "skipped",
                  reason="border-cut object"),
            Event(2, f"{REJECTED_PREFIX}border-cut object (box [0, 1, 2, 3] at 520 mm)", "skipped",
                  reason="border-cut object"),
            Event(1, f"{REJECTED_PREFIX}implausibly sized object, 900×800 mm (box [1, 1, 9, 9] at 2 m)", "skipped",
                  reason="implausibly sized object")]


def test_the_not_estimated_warning_comes_from_the_reasons_not_the_messages():
    trace = _unestimated(REJECTED)
    expected = ("massviz estimate: warning: r: not estimated: only border-cut / implausibly sized objects: "
                "2 × border-cut object (frames 0–2), 1 × implausibly sized object (frame 1); 1 other detection(s) "
                "with depth not chosen (score <= threshold or excluded)")
    assert flag_warning("estimate", trace) == expected
    assert [e.message for e in trace.events if e.kind == "not_estimated"] == [
        expected.split("not estimated: ")[1] + ": mass not estimated (-1)"]
    # other wording of the events (or of the not_estimated line) does not change what is counted
    reworded = [e._replace(message=f"rejected #{j}") for j, e in enumerate(REJECTED)]
    assert flag_warning("estimate", _unestimated(reworded)) == expected
    odd = dataclasses.replace(trace, events=[e._replace(message="?") if e.kind == "not_estimated" else e
                                             for e in trace.events])
    assert flag_warning("estimate", odd) == expected
    # a skipped event without a reason (a mask without depth) is no rejected object
    plain = [Event(0, f"{REJECTED_PREFIX}border-cut object (box ...)", "skipped")]
    assert why_not_estimated(trace.detections, plain) == NotEstimated()
    assert flag_warning("estimate", _unestimated(plain)) is None


def test_a_file_written_before_reasons_gets_them_from_its_events(rec, tmp_path):
    trace = _unestimated(REJECTED)
    path = save_trace(trace, tmp_path / "new.npz")
    assert load_trace(path).events == trace.events  # the reasons are saved
    old = dataclasses.replace(trace, events=[e._replace(reason="") for e in trace.events])
    loaded = load_trace(save_trace(old, tmp_path / "old.npz"))
    assert [e.reason for e in loaded.events] == [e.reason for e in trace.events]
    assert flag_warning("log", loaded) == flag_warning("log", trace) is not None


def test_the_depth_detector_rejections_reach_the_events_with_their_reason(tmp_path):
    from massviz.detect.depth import DepthDetector

    depth = np.full((120, 160), 1500, np.uint16)
    depth[90:120, 0:30] = 500  # cut by the bottom-left corner: the only object
    recording = open_recording(write_recording(tmp_path / "cut", [np.zeros((120, 160, 3), np.uint8)], [depth]))
    trace = run(recording, DepthDetector(threshold=0.0), DistanceModel(), prefetch=0)
    skipped = [e for e in trace.events if e.kind == "skipped"]
    assert [(e.reason, e.message) for e in skipped] == [
        ("border-cut object", f"{REJECTED_PREFIX}{Rejection('border-cut object', 'border-cut object (box [0, 90, 30, 120] at 500 mm)')}")]
    assert trace.estimate == -1
    assert flag_warning("estimate", trace).endswith("not estimated: only border-cut / implausibly sized objects: "
                                                    "1 × border-cut object (frame 0)")


# ------------------------------------------------------------------------------------------ one selection, sinks
def test_a_finished_trace_gives_a_sink_the_results_the_run_gave(rec):
    # what a sink is given for a trace from the cache (frame_results) is what it was given during the run
    seen = []
    trace = run(rec, ListDetector(DETECTIONS), DistanceModel(), selection=Selection(k=2, threshold=0.6), prefetch=0,
                on_frame=lambda frame, result: seen.append(result))
    replayed = [r for _, r in frame_results(trace, rec.frames(indices=[int(f) for f in trace.frames]))]
    assert len(replayed) == len(seen) == len(trace.frames)
    for a, b in zip(seen, replayed, strict=False):
        assert a.offset == b.offset and a.frame.index == b.frame.index
        assert a.selection.tolist() == b.selection.tolist() and a.running_estimate == b.running_estimate
        assert a.active.tolist() == b.active.tolist() == np.flatnonzero(a.detections.score > 0.6).tolist()
        assert a.detections.xyxy.tolist() == b.detections.xyxy.tolist()
        assert all(np.array_equal(p, q) for p, q in zip(a.patches, b.patches, strict=False))
    assert any(len(r.active) < len(r.detections) for r in seen)  # the threshold removed some: the check can fail


def test_the_selection_is_resolved_once_from_the_options_and_the_detector():
    from massviz.app import Pipeline, PipelineOptions

    det = ListDetector(DETECTIONS, threshold=0.45)
    pipeline = Pipeline(PipelineOptions(k=3, stride=2), det, DistanceModel(), None)
    assert pipeline.selection == Selection(k=3, threshold=0.45, stride=2) and pipeline.threshold == 0.45
    named = Pipeline(PipelineOptions(k=3, threshold=0.7), det, DistanceModel(), None)
    assert named.selection.threshold == 0.7
    with pytest.raises(ValueError, match="below the score cut 0.45 of the detector"):
        Selection(threshold=0.3).at_cut(0.45)


def test_every_threshold_below_the_score_cut_is_refused_by_one_rule(rec, tmp_path):
    """Wherever a selection threshold meets the score cut its detections were kept at (the detector's, a trace's,
    the retuning sliders', the sweep table's, a cached trace's index), a threshold below it is refused with the one
    rule's error (a MassvizError and a ValueError, naming both values and the run that would serve it); one at the
    cut, or a float round trip below it, is accepted everywhere."""
    from massviz.core.selection import BelowCutError
    from massviz.evaluation.runs import trace_from_index
    from massviz.evaluation.sweep import SweepTable
    from massviz.evaluation.tuning import retuned_selection
    from massviz.io.cache import TraceIndex

    trace = run(rec, ListDetector(DETECTIONS, threshold=0.4), DistanceModel(), k=3)
    index = TraceIndex(recording=trace.recording, detector=dict(trace.detector), detect_threshold=0.4,
                       stride=1, weights_id="w", frames=trace.frames, detections=trace.detections,
                       trace_path=tmp_path / "scene.npz")
    places = {
        "Selection.at_cut": lambda t: Selection(threshold=t).at_cut(0.4),
        "Trace.reselect": lambda t: trace.reselect(threshold=t),
        "retuned_selection": lambda t: retuned_selection(trace, k=3, threshold=t),
        "SweepTable.chosen": lambda t: SweepTable([trace]).chosen(t, 3),
        "trace_from_index": lambda t: trace_from_index(index, k=3, threshold=t),
    }
    for where, call in places.items():
        with pytest.raises(BelowCutError, match=r"threshold 0\.39 is below the score cut 0\.4 of .*--threshold 0\.39"
                           ) as err:
            call(0.39)
        assert isinstance(err.value, MassvizError) and isinstance(err.value, ValueError), where
        call(0.4)
        call(float(np.float32(0.4)) - 5e-10)  # a threshold that went through a float32 column


def test_detections_grouped_by_frame():
    dets = Detections(frame=[3, 1, 3, 1, 7], xyxy=np.tile([0, 0, 2, 2], (5, 1)), score=[0.5] * 5,
                      class_id=[47] * 5)
    groups = dets.indices_by_frame()
    assert list(groups) == [1, 3, 7]
    assert {f: g.tolist() for f, g in groups.items()} == {1: [1, 3], 3: [0, 2], 7: [4]}
    assert Detections().indices_by_frame() == {}


def test_retune_is_one_reselect_with_the_result_of_the_step_by_step_chain(rec, analyses):
    from massviz.evaluation.tuning import original_selection, retune, retuned_estimate, retuned_selection, subsample

    trace = made(rec)
    exclude = [int(trace.selection[0])]
    for stride, k in ((1, 2), (2, 2), (3, 1)):
        analyses.clear()
        one = retune(trace, k=k, stride=stride, exclude=exclude)
        assert len(analyses) == 1
        chain = subsample(trace.reselect(exclude=exclude), stride).reselect(k=k)
        assert len(analyses) == 1 + (2 if stride == 1 else 3)  # the chain analyses every intermediate trace
        assert one.selection.tolist() == chain.selection.tolist() and one.estimate == chain.estimate
        assert one.excluded.tolist() == chain.excluded.tolist() and one.events == chain.events
        assert one.flags == chain.flags and one.stride == chain.stride
        # the selection stage alone selects the same, of the trace or of its columns only (a selection index)
        sel = retuned_selection(trace, k=k, threshold=trace.threshold, stride=stride, exclude=exclude)
        assert sel.tolist() == original_selection(trace, one, stride).tolist()
        columns = dataclasses.replace(trace.detections, masks=[None] * len(trace.detections),
                                      patches=[None] * len(trace.detections))
        index = type("Index", (), {"detections": columns, "detect_threshold": trace.detect_threshold})()
        assert retuned_estimate(index, k=k, threshold=trace.threshold, stride=stride,
                                exclude=exclude) == one.estimate
    with pytest.raises(MassvizError, match="below the score cut 0.4 of these detections"):
        retuned_selection(trace, k=2, threshold=trace.detect_threshold - 0.1)


def test_a_subsampled_trace_keeps_the_measurements_of_its_detections_renumbered(rec):
    from massviz.core.measurement import Measurement
    from massviz.evaluation.tuning import kept_indices, retune

    trace = made(rec)
    fake = [Measurement(rank=r, detection=int(i), frame=int(trace.detections.frame[i]), height_mm=1.0,
                        width_mm=10.0 + i, depth_mm=1.0, center=[0, 0, 1], extent=[0.1, 0.1, 0.1],
                        R=np.eye(3).tolist(), n_points=10) for r, i in enumerate(trace.selection)]
    measured = dataclasses.replace(trace, measurements=fake)
    sub = retune(measured, stride=2)
    keep = kept_indices(trace, 2)
    for m in sub.measurements:
        original = int(keep[m.detection])
        assert m.width_mm == 10.0 + original and m.detection in sub.selection.tolist()
    assert len(sub.measurements) == len(set(sub.selection.tolist()) & {int(np.flatnonzero(keep == i)[0])
                                                                      for i in trace.selection if i in keep})


def test_a_light_recording_takes_the_patches_the_trace_dropped_from_the_frames_results(rec):
    from massviz.views.rerun_dataset import _patch_images

    trace = made(rec)
    dets = trace.detections
    kept, best = _patch_images(trace, rec)
    assert set(kept) == {int(i) for i in trace.selection} and best is not None
    dropped = dataclasses.replace(trace, detections=dataclasses.replace(dets, patches=[None] * len(dets)))
    again, best_again = _patch_images(dropped, rec)
    assert set(again) == set(kept) and np.array_equal(best, best_again)
    assert all(np.array_equal(again[i], kept[i]) for i in kept)  # as the pipeline cut them
