"""A screenshot of the rerun web viewer showing a run's recording (its 4D mesh sequence), taken by a
real headless Chromium (Debian package ``chromium``), for the README.

    python bench/viewer_screenshot.py [--run-dir RUN [--reuse]]  [--out docs/viewer.png]

Without ``--run-dir`` it first makes a small cube run (16 frames, 1/6 s apart: t = 0 .. 2.5 s).
Then ``python -m tivne.view`` writes run/view.rrd (meshes every 5th frame), ``rerun view.rrd
--serve-web`` serves it on localhost with the web viewer, and Chromium (software WebGL:
SwiftShader) loads the viewer; the time cursor opens at t = 0 (not yet mid-sequence: a
``#when=frame@10`` URL fragment left it at 0, ``#when=scene_time@1.667s`` and a recording cut at
1.667 s with a "following" time panel (``tivne.view until=1.667``) left the viewer on its welcome
page on this machine; see the note of issue 22). Once the
viewer has started (its "Loading" text is gone), its page has changed from the welcome page it
shows before the recording arrives, and ``--settle`` more seconds have passed, the page is
saved as a PNG over the DevTools protocol (Chromium's own ``--screenshot`` fires before the viewer's
WebAssembly has started). Needs ``aiohttp`` for the DevTools websocket. Prints the commands it ran,
what the page said and the PNG's size.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
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


async def devtools_screenshot(port: int, out: Path, timeout: float, settle: float, size: tuple[int, int]) -> str:
    """Wait for the viewer page to start (no "Loading" text left, up to ``timeout`` s), wait
    ``settle`` s more, save a PNG of the page; returns the page's text at that point."""
    import aiohttp

    async with aiohttp.ClientSession() as http:
        async with http.get(f"http://127.0.0.1:{port}/json") as resp:
            page = next(t for t in await resp.json(content_type=None) if t["type"] == "page")
        async with http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
            ids = iter(range(1, 10**6))

            async def call(method: str, **params):
                msg_id = next(ids)
                await ws.send_str(json.dumps({"id": msg_id, "method": method, "params": params}))
                async for msg in ws:
                    data = json.loads(msg.data)
                    if data.get("id") == msg_id:
                        return data.get("result", {})
                raise RuntimeError("DevTools connection closed")

            await call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)

            async def capture() -> bytes:
                return base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])

            end, text = time.time() + timeout, ""
            while time.time() < end:  # the WebAssembly bundle loads and starts
                result = await call("Runtime.evaluate", expression="document.body ? document.body.innerText : ''")
                text = str(result.get("result", {}).get("value", ""))
                if "Loading" not in text:
                    break
                await asyncio.sleep(2)
            # The viewer first shows its welcome page, then connects to the server and draws the
            # recording: wait until the page changes from that first look, then let it draw.
            first = shot = await capture()
            while time.time() < end and abs(len(shot) - len(first)) < 0.3 * len(first):
                await asyncio.sleep(5)
                shot = await capture()
            await asyncio.sleep(settle)
            out.write_bytes(await capture())
            return text


def run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    print("$ " + " ".join(cmd), flush=True)
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_WAIT_POLICY="PASSIVE")
    return subprocess.run(cmd, cwd=REPO, env=env, check=True, **kw)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path)
    parser.add_argument("--reuse", action="store_true", help="use run_dir/view.rrd as it is")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "viewer.png")
    parser.add_argument("--size", default="1400,860")
    parser.add_argument("--timeout", type=float, default=240.0, help="seconds to wait for the viewer to start")
    parser.add_argument("--settle", type=float, default=15.0, help="seconds to let it draw once the recording shows")
    args = parser.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("error: chromium not found (apt-get install -y chromium)")
    work = Path(tempfile.mkdtemp(prefix="tivne-shot-"))
    run_dir = args.run_dir or work / "cube"
    if args.run_dir is None:
        run([sys.executable, "-m", "tivne.train", *CUBE, f"hydra.run.dir={run_dir}"], stdout=subprocess.DEVNULL)
    rrd = run_dir / "view.rrd"
    if not (args.reuse and rrd.is_file()):
        run([sys.executable, "-m", "tivne.view", f"run_dir={run_dir}", "every=5", "mesh.resolution=0.03"])
    web, grpc = free_port(), free_port()
    rerun_bin = Path(sys.executable).with_name("rerun")
    server = subprocess.Popen([str(rerun_bin), str(rrd), "--serve-web", "--web-viewer-port", str(web),
                               "--port", str(grpc)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_for(web)
        wait_for(grpc)
        inner = f"rerun+http://127.0.0.1:{grpc}/proxy"
        url = f"http://127.0.0.1:{web}/?url={urllib.parse.quote(inner, safe='')}"
        args.out.parent.mkdir(parents=True, exist_ok=True)
        profile = work / "chromium-profile"
        profile.mkdir()
        devtools = free_port()
        cmd = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={args.size}",
               f"--remote-debugging-port={devtools}", url]
        print("$ " + " ".join(cmd), flush=True)
        browser = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait_for(devtools)
            width, height = (int(v) for v in args.size.split(","))
            text = asyncio.run(devtools_screenshot(devtools, args.out, args.timeout, args.settle, (width, height)))
            print(f"page text when taken: {text[:300]!r}")
        finally:
            browser.terminate()
            browser.wait(timeout=30)
    finally:
        server.terminate()
        server.wait(timeout=20)
    size = args.out.stat().st_size if args.out.is_file() else 0
    print(f"screenshot: {args.out} ({size} bytes) of {url}")


if __name__ == "__main__":
    main()
