"""A latent frame of each `--mode` (causal, nearest, fused) at the same time on a real recording, beside the APS
frames before and after it: what each mode shows between two APS frames. Runs the node as a user would (--out) and
reads its frames back.

    python -m tools.modes_figure docs/modes_real.png [--recording FILE.aedat4] [--between K]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import Frame
from tools.figure import _fit, _label, load_recording, write_rows
from tools.real_camera_figure import REAL


def frames_of(path: Path) -> list[Frame]:
    with Aedat4Reader(path) as reader:
        return [item for _, item in reader if isinstance(item, Frame)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--recording", type=Path, default=REAL / "emlb_demo-01_davis346.aedat4")
    ap.add_argument("--between", type=int, default=6, help="show the time halfway between APS frames K and K+1")
    args = ap.parse_args(argv)
    _, aps = load_recording(args.recording)
    k = min(args.between, len(aps) - 2)
    t = (aps[k].mid_exposure_us + aps[k + 1].mid_exposure_us) // 2
    gain = 255.0 / max(1.0, float(np.percentile(aps[k].image, 99.5)))
    tiles = [_label(aps[k].image * gain, f"APS frame {k}")]
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("causal", "nearest", "fused"):
            out = Path(tmp) / f"{mode}.aedat4"
            subprocess.run([sys.executable, "-m", "edi_live", "--replay", str(args.recording), "--speed", "0",
                            "--no-publish", "--mode", mode, "--every", "300", "--out", str(out)], check=True,
                           capture_output=True)
            # an --out frame's exposure window is its latent time; pick the one nearest the midpoint
            lo, hi = aps[k].mid_exposure_us, aps[k + 1].mid_exposure_us
            inside = [f for f in frames_of(out) if lo < f.exposure_start_us < hi]
            best = min(inside, key=lambda f: abs(f.exposure_start_us - t))
            after_ms = (best.exposure_start_us - aps[k].mid_exposure_us) / 1000
            tiles.append(_label(best.image * gain, f"{mode}: APS {k} + {after_ms:.1f} ms"))
    tiles.append(_label(aps[k + 1].image * gain, f"APS frame {k + 1}"))
    write_rows([np.hstack(_fit(tiles, 200))], args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
