"""``massviz live``: a RealSense camera (or a RealSense file played back in real time) through the pipeline, frame by
frame, logged to Rerun as it happens."""
from __future__ import annotations

import argparse
import sys

from massviz.commands._common import PIPELINE_HELP, add_pipeline_args

EPILOG = """examples:
  massviz live --rrd session.rrd --save rec/ --duration 20     first connected camera, 20 s
  massviz live --camera 123456789012 --spawn                     that camera, into a native Rerun viewer
  massviz live --file handover.db3 --serve-web                   a recording in real time, in a browser viewer
  massviz log rec/ --rrd replay.rrd                              replay a saved session (same trace, from cache)

Per processed frame: detect, features, predict, update the K nearest so far, and log the frame's stages at once
(/camera/*, /patches/<rank>, /predictions/running_estimate, /latency/<stage> in ms; entity tree in docs/entity-tree.md).
When the detector is slower than the camera, massviz takes the newest frame and drops the others: the drops are
counted in /log and in the summary; nothing queues. Ctrl-C (or SIGTERM/SIGHUP), --duration or the end of a --file
ends the session: the trace goes to the trace cache, --save writes the processed frames as a massviz recording
folder, and the last lines print the estimate and, when chosen patches look like another object, a warning with
the estimate without them (the tiles of those patches are then marked flagged at the last frame); a second Ctrl-C
interrupts at once and writes nothing. Needs
pyrealsense2: pip install 'massviz[realsense]'.
""" + PIPELINE_HELP


def register(sub) -> None:
    p = sub.add_parser(
        "live", help="run a RealSense camera (or a .db3/.bag in real time) live and log every frame to Rerun",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Estimate the container's mass live from an Intel RealSense camera (or a RealSense recording "
        "played back in real time), streaming each frame's stages to Rerun as they are computed.",
        epilog=EPILOG)
    src = p.add_argument_group("source (default: the first connected camera)")
    one = src.add_mutually_exclusive_group()
    one.add_argument("--camera", metavar="SERIAL", nargs="?", const="",
                     help="a connected RealSense camera by serial number (no serial: the first one)")
    one.add_argument("--file", metavar="X.db3", help="a RealSense recording (.db3 or .bag) played back in real time")
    src.add_argument("--width", type=int, default=640, help="camera stream width (default 640)")
    src.add_argument("--height", type=int, default=480, help="camera stream height (default 480)")
    src.add_argument("--fps", type=int, default=30, help="camera frame rate (default 30)")
    out = p.add_argument_group("output (any of them)")
    out.add_argument("--rrd", metavar="OUT.rrd", help="write the Rerun recording to this file (when the session ends)")
    out.add_argument("--spawn", action="store_true", help="spawn (or connect to) a native Rerun viewer")
    out.add_argument("--connect", metavar="URL", help="send to a running Rerun viewer or server, e.g. "
                     "rerun+http://127.0.0.1:9876/proxy")
    out.add_argument("--serve-web", action="store_true",
                     help="serve a browser viewer on 127.0.0.1 (ports --web-port and --grpc-port) while the session "
                     "runs; its server ends with the command (an open page keeps what it received)")
    out.add_argument("--web-port", type=int, default=9090, help="--serve-web: web viewer port (default 9090)")
    out.add_argument("--grpc-port", type=int, default=9876, help="--serve-web: gRPC port (default 9876)")
    out.add_argument("--save", metavar="REC_DIR", help="write the processed frames as a massviz recording folder "
                     "(a new folder; written when the session ends)")
    p.add_argument("--duration", type=float, metavar="S", help="end after S seconds (default: Ctrl-C or end of file)")
    add_pipeline_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from massviz.commands._common import build
    from massviz.errors import MassvizError
    from massviz.io.formats import realsense_decode, realsense_live

    if args.stride != 1:
        raise MassvizError("--stride does not apply to live mode (it processes the newest frame each time)")
    if args.rrd and Path(args.rrd).is_dir():
        raise MassvizError("is a directory; --rrd needs a file path", args.rrd)
    if args.rrd and not Path(args.rrd).parent.is_dir():
        raise MassvizError(f"cannot write: folder {Path(args.rrd).parent} does not exist", args.rrd)
    if args.save and Path(args.save).exists() and (not Path(args.save).is_dir() or any(Path(args.save).iterdir())):
        raise MassvizError("exists and is not an empty folder; --save needs a new folder", args.save)
    if args.serve_web and args.connect:
        raise MassvizError("give --connect or --serve-web, not both")
    if args.connect:  # else Rerun's sink retries in the background, then drops what it could not send
        from massviz.io.endpoint import host_port, reach_grpc

        host, port = host_port(args.connect, "--connect")
        reach_grpc("--connect", args.connect, host, port, hint="start a viewer first (`rerun` listens on "
                   "rerun+http://127.0.0.1:9876/proxy), or use --serve-web or --rrd")
    realsense_decode.import_rs()
    if args.file:
        stream = realsense_live.open_file_stream(args.file)
        name = Path(args.file).stem
        stream.option = f"--file {args.file}"
    else:
        stream = realsense_live.open_camera(args.camera or None, args.width, args.height, args.fps)
        serial = stream.info.device.get('serial', 'realsense')
        name = f"camera-{serial}"
        stream.option = f"--camera {args.camera or serial}"
    try:
        pipeline = build(args)
    except BaseException:
        stream.stop()
        raise
    return run_session(args, pipeline, stream, name)


def run_session(args, pipeline, stream, name: str) -> int:
    """The session itself (``massviz live`` after the source is open; tests call it with a stand-in camera)."""
    from massviz.commands._common import flag_warning
    from massviz.core.types import RecordingInfo
    from massviz.runners.camera_loop import run_live

    info = stream.info
    rec_info = RecordingInfo(id=name, path=str(args.file or stream.description), kind="live", width=info.width,
                             height=info.height, num_frames=0, fps=info.fps, intrinsics=info.intrinsics,
                             meta={"realsense": info.describe()})
    fp = pipeline.frame_pipeline(rec_info)
    logger = None
    web = None
    try:  # the web server ends with the session, however it ends
        try:
            connect = args.connect
            if args.serve_web:
                from massviz.errors import MassvizError
                from massviz.views.web_viewer import WebViewer, port_in_use

                for port in (args.web_port, args.grpc_port):
                    if port and port_in_use(port):
                        raise MassvizError(f"port {port} on 127.0.0.1 is in use; choose others with --web-port/"
                                           "--grpc-port")
                web = WebViewer(port=args.web_port, grpc_port=args.grpc_port, timeout=20.0)
                connect = connect or web.grpc
                print(f"massviz live: web viewer at {web.url}", file=sys.stderr)
            if args.rrd or args.spawn or connect:
                from massviz.views.rerun.live_logger import LiveLogger

                logger = LiveLogger(name=name, k=fp.selection.k,
                                    intrinsics=info.intrinsics, rrd=args.rrd, spawn=args.spawn, connect=connect)
            print(f"massviz live: {stream.description}; Ctrl-C ends the session", file=sys.stderr)
            result = run_live(stream, fp, logger=logger, duration=args.duration, save=args.save,
                              progress=not args.quiet, name=name, source=stream.description)
        except BaseException as err:  # (a signal too) run_live ends the stream and logger itself; before it starts,
            stream.stop()  # this does (both idempotent)
            if logger is not None:
                logger.abort(err)
            raise
        trace, stats = result.trace, result.stats
        cached = _cache(pipeline, trace, result, args, stream)
    finally:
        if web is not None:
            web.stop()
    print(f"massviz live: {stats.summary()}; stopped: {stats.stopped}", file=sys.stderr)
    for line in ([f"wrote {args.rrd}"] if args.rrd else []) + ([f"saved the frames to {result.saved} "
                                                                 f"(replay: massviz log {result.saved} --rrd X.rrd)"]
                                                                if result.saved else []) + \
            ([f"trace cached at {cached}"] if cached else []) + \
            (["stopped the web viewer's server (an open page keeps what it received; --rrd keeps the recording)"]
             if web is not None else []):
        print(f"massviz live: {line}", file=sys.stderr)
    est = "not estimated" if trace.estimate < 0 else f"{trace.estimate:.1f} g"
    n, k = len(trace.selection), int(trace.k)
    chosen = f"K={k}" if n >= k else f"{n} of K={k}"  # fewer detections than K: say how many were chosen
    print(f"{name}: {est} ({chosen}, {stats.processed} frames, {stats.dropped} dropped)", file=sys.stderr)
    warning = flag_warning("live", trace)
    if warning:
        print(warning, file=sys.stderr)
    return 0


def _cache(pipeline, trace, result, args, stream):
    """Put the session's trace in the trace cache under the recording it is exactly the trace of: the saved folder,
    else the played file when every frame of it was processed, else a session file under the cache's live/."""
    import re
    import time

    if pipeline.cache is None:
        return None
    from massviz.core.detector import detector_info
    from massviz.io.recording import open_recording

    info = detector_info(pipeline.detector)
    if result.saved is not None:  # the recording the folder writer wrote (not read back)
        return pipeline.cache.save(trace, result.recording, info)
    if args.file:
        import dataclasses

        rec = stream.recording if stream.recording is not None else open_recording(args.file)
        numbers = rec.meta.get("realsense", {}).get("frame_numbers")
        if result.stats.dropped == 0 and numbers == result.stats.frame_numbers:
            from massviz.core.trace import analyse_trace

            return pipeline.cache.save(analyse_trace(dataclasses.replace(trace, recording=rec.info())), rec, info)
    from massviz.io.trace_file import save_trace

    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", trace.recording.id)
    return save_trace(trace, pipeline.cache.root / "live" / f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}.npz")
