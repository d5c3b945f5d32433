"""The documentation's picture of the web view (docs/how-to/monitoring.md): ``docs/web-view.png``.

    python docs/make_screenshot.py [--profile short-test] [--minutes 18] [--speedup 20] [--out docs/web-view.png]

Simulates ``--minutes`` of a thermal run at 100 Hz (the simulator, seed 3), serves it to ``fog-driver run
--http`` through ``replay://`` at ``--speedup`` times its pace, opens the page in headless Chromium
(Playwright; ``apt-get install chromium``) and takes the screenshot once the replay is near its end.  The
plots are over device time, so a faster replay draws them as the real run would.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profile", default="short-test")
    parser.add_argument("--minutes", type=float, default=18.0)
    parser.add_argument("--speedup", type=float, default=20.0)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "web-view.png")
    args = parser.parse_args()
    from playwright.sync_api import expect, sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        sys.exit("needs Chromium: apt-get install chromium")
    rate_hz = 100
    with tempfile.TemporaryDirectory(prefix="fog-shot-") as tmp:
        capture = Path(tmp) / "run.bin"
        subprocess.run(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "simulate",
                "--profile",
                args.profile,
                "--rate-hz",
                str(rate_hz),
                "--seed",
                "3",
                "--duration",
                str(args.minutes * 60),
                "--out",
                str(capture),
            ],
            check=True,
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
        )
        frames = int(args.minutes * 60 * rate_hz)
        daemon = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "run",
                "--port",
                f"replay://{capture}?rate={rate_hz * args.speedup:g}",
                "--listen",
                "127.0.0.1:0",
                "--http",
                "127.0.0.1:0",
                "--capture-dir",
                str(Path(tmp) / "captures"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            cwd=ROOT,
        )
        try:
            url = re.search(r"web view on (http://\S+/)", daemon.stdout.readline()).group(1)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
                page = browser.new_page(viewport={"width": 1280, "height": 900})
                page.goto(url)
                expect(page.locator("#page-state")).to_have_text("live", timeout=30_000)
                last = int(0.97 * frames)  # near the end, while samples still flow
                timeout_ms = (args.minutes * 60 / args.speedup + 60) * 1000
                frames_shown = 0
                while frames_shown < last:
                    text = page.locator("#status-frames").inner_text()
                    frames_shown = int(text.replace(",", "")) if text.replace(",", "").isdigit() else 0
                    expect(page.locator("#status-frames")).not_to_have_text(text, timeout=timeout_ms)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(args.out), full_page=True)
                browser.close()
        finally:
            daemon.terminate()
            daemon.wait(30)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
