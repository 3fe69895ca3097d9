"""``massviz samples``: write the synthetic hand-over recordings (with ground truth) that tests and demos use."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm


def register(subparsers) -> None:
    from massviz.samples.specs import N_FRAMES, SAMPLES

    parser = subparsers.add_parser(
        "samples",
        help="generate the synthetic sample recordings (data_samples/)",
        description="Render small synthetic RGB-D hand-over recordings with ground truth, deterministically (the same "
        "code writes the same bytes). A person hands over a cup, a transparent glass or a box while a pitcher stands "
        "on the table, nearer to the camera than the container early in the hand-over (in cup_handover it is lifted "
        "towards the camera for a few frames, nearer than the cup ever comes). Each recording has "
        f"{N_FRAMES} frames at 480x270: rgb/, depth/ (16-bit mm), gt/ (instance ids), intrinsics.json, meta.json. "
        "A recording is written to a temporary folder and renamed into place, replacing the previous one.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--out", type=Path, default=Path("data_samples"), help="folder to write the recordings into")
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=sorted(SAMPLES),
                        help=f"generate only these recordings (of: {', '.join(SAMPLES)})")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from massviz.samples.generator import N_FRAMES, SAMPLES, write_sample

    names = args.only or list(SAMPLES)
    from massviz.io.atomic import check_output_dir

    check_output_dir(args.out, "--out")
    from massviz.io.atomic import check_replaceable
    from massviz.samples.generator import SAMPLE_FILES

    for name in names:  # every recording it replaces, before the first is rendered
        check_replaceable(args.out / name, SAMPLE_FILES, "sample recording", link_ok=False)
    with tqdm(total=N_FRAMES * len(names), desc="rendering", unit="frame", file=sys.stderr) as bar:
        for name in names:
            bar.set_postfix_str(name)
            path = write_sample(SAMPLES[name], args.out, progress=bar.update)
            tqdm.write(f"wrote {path}", file=sys.stderr)
    return 0
