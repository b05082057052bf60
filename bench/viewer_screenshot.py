"""A screenshot of the rerun web viewer showing a run's recording at a mid-sequence time, taken by a
real headless Chromium (Debian package ``chromium``), for the README.

    python bench/viewer_screenshot.py [--run-dir RUN] [--frame 10] [--out docs/viewer.png] [--keep]

Without ``--run-dir`` it first makes a small cube run (16 frames, 1/6 s apart: t = 0 .. 2.5 s).
Then ``python -m tivne.view`` writes run/view.rrd (meshes every 5th frame), ``rerun view.rrd
--serve-web`` serves it on localhost with the web viewer, and Chromium (software WebGL:
SwiftShader) loads the viewer with the time cursor at ``--frame`` (``#when=frame@N``) and saves the
PNG. Prints the commands it ran and the PNG's size; a blank or failed render is reported as such.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CUBE = ["experiment=smoke", "dataset.width=160", "dataset.height=120", "dataset.cache_dir=null", "data.stride=5",
        "data.max_frames=16", "mapping.iters=6", "mesh.resolution=0.03"]
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-gl=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(port: int, timeout: float = 60.0) -> None:
    end = time.time() + timeout
    while time.time() < end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.5)
    raise TimeoutError(f"nothing listens on port {port} after {timeout:.0f} s")


def run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    print("$ " + " ".join(cmd), flush=True)
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_WAIT_POLICY="PASSIVE")
    return subprocess.run(cmd, cwd=REPO, env=env, check=True, **kw)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path)
    parser.add_argument("--frame", type=int, default=10)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "viewer.png")
    parser.add_argument("--size", default="1400,860")
    parser.add_argument("--wait-ms", type=int, default=40000, help="Chromium's virtual time budget for loading and drawing")
    args = parser.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("error: chromium not found (apt-get install -y chromium)")
    work = Path(tempfile.mkdtemp(prefix="tivne-shot-"))
    run_dir = args.run_dir or work / "cube"
    if args.run_dir is None:
        run([sys.executable, "-m", "tivne.train", *CUBE, f"hydra.run.dir={run_dir}"], stdout=subprocess.DEVNULL)
    run([sys.executable, "-m", "tivne.view", f"run_dir={run_dir}", "every=5", "mesh.resolution=0.03"])
    web, grpc = free_port(), free_port()
    rerun_bin = Path(sys.executable).with_name("rerun")
    server = subprocess.Popen([str(rerun_bin), str(run_dir / "view.rrd"), "--serve-web", "--web-viewer-port", str(web),
                               "--port", str(grpc)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_for(web)
        wait_for(grpc)
        inner = f"rerun+http://127.0.0.1:{grpc}/proxy#when=frame@{args.frame}"
        url = f"http://127.0.0.1:{web}/?url={urllib.parse.quote(inner, safe='')}"
        args.out.parent.mkdir(parents=True, exist_ok=True)
        profile = work / "chromium-profile"
        profile.mkdir()
        run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={args.size}",
             f"--virtual-time-budget={args.wait_ms}", f"--screenshot={args.out}", url], timeout=300,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    finally:
        server.terminate()
        server.wait(timeout=20)
    size = args.out.stat().st_size if args.out.is_file() else 0
    print(f"screenshot: {args.out} ({size} bytes) of {url}")


if __name__ == "__main__":
    main()
