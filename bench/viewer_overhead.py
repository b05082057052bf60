"""What ``viewer=rerun`` costs a run: the same cube run with and without the recorder, alternated
in one session (A B A B ...), so both see the same machine load.

    python bench/viewer_overhead.py [--pairs 2] [overrides ...]     # default: 60 frames at 320x240

Prints s/frame (mean over frames after the first) of each run, the overhead in percent of the
median pair, the time spent inside the recorder's calls per frame (measured in the run itself, so
it does not depend on the load of a shared machine as much as the A/B difference does), the recording's size, and whether the two trajectories are identical (the viewer only
reads the run: renders at the estimated pose are deterministic and draw no random numbers).
Extra arguments are Hydra overrides of conf/config.yaml. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

import tivne.slam.run  # noqa: E402
from data_modules.tables import read_tum_trajectory  # noqa: E402
from tivne.cli import register_defaults  # noqa: E402
from tivne.slam.run import run  # noqa: E402

register_defaults()  # the config nodes conf/*.yaml compose onto

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


class Timed:
    """Wraps the run's observer and adds up the seconds spent in its calls."""

    seconds = 0.0
    by_call: dict[str, float] = {}

    def __init__(self, inner) -> None:
        self.inner = inner

    def __getattr__(self, name: str):
        method = getattr(self.inner, name)

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                took = time.perf_counter() - start
                Timed.seconds += took
                Timed.by_call[name] = Timed.by_call.get(name, 0.0) + took

        return timed


make_observer = tivne.slam.run.make_observer
tivne.slam.run.make_observer = lambda *a, **k: Timed(make_observer(*a, **k))

BASE = ["dataset=cube", "dataset.width=320", "dataset.height=240", "data.max_frames=60", "output.evaluate=false",
        "trainer.progress_bar=false"]


def one_run(overrides: list[str], viewer: bool, root: Path) -> tuple[float, float, Path]:
    """(s/frame after the first, recorder seconds per frame, run dir)."""
    run_dir = root / f"run{len(list(root.iterdir()))}"
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[*BASE, *overrides, f"viewer={'rerun' if viewer else 'none'}"])
    Timed.seconds, Timed.by_call = 0.0, {}
    metrics = run(cfg, run_dir)
    return float(metrics["s_per_frame_after_first"]), Timed.seconds / metrics["frames"], run_dir


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2)
    args, overrides = parser.parse_known_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        pairs, shares = [], []
        for i in range(args.pairs):
            without, _, dir_a = one_run(overrides, False, root)
            with_viewer, inside, dir_b = one_run(overrides, True, root)
            same = bool((read_tum_trajectory(dir_a / "trajectory.txt")[1] == read_tum_trajectory(dir_b / "trajectory.txt")[1]).all())
            size = (dir_b / "viewer.rrd").stat().st_size / 1e6
            pairs.append(with_viewer / without - 1)
            shares.append(inside / with_viewer)
            print(f"pair {i}: without {without:.4f} s/frame, with viewer {with_viewer:.4f} s/frame ({100 * pairs[-1]:+.1f} %); "
                  f"in the recorder {1000 * inside:.1f} ms/frame ({100 * shares[-1]:.1f} % of s/frame, meshes included); "
                  f"viewer.rrd {size:.1f} MB; identical trajectories: {same}", flush=True)
            print("  recorder seconds by call: " + ", ".join(f"{k} {v:.2f}" for k, v in sorted(Timed.by_call.items())), flush=True)
        print(f"viewer overhead, median of {len(pairs)} pairs: A/B {100 * statistics.median(pairs):+.1f} % of s/frame; "
              f"time in the recorder {100 * statistics.median(shares):.1f} % of s/frame")


if __name__ == "__main__":
    main()
