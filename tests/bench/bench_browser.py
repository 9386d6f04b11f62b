#!/usr/bin/env python3
"""
The browser viewer's own numbers (not run by ctest), in headless Chromium on the page volfxd
--http serves: frames a second drawn by the page at 640x360 while the demo scene plays (at the
page's 30 fps request and at 60), and the latency from a slider move (the exposure, on the
paused scene) to the first frame drawn that shows it, median and p90 of --moves moves.

    python3 tests/bench/bench_browser.py --bin build/bin
    python3 tests/bench/bench_browser.py --bin build/bin --seconds 20 --moves 40
"""

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "browser"))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import browser  # noqa: E402

browser.ensure_selenium()
import mock  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402

LATENCY_JS = """
const n = arguments[0], done = arguments[arguments.length - 1];
const v = window.volfxViewer;
const slider = document.querySelector('input[type=range][data-path="render.exposure"]');
const canvas = document.getElementById('view'), ctx = canvas.getContext('2d');
const mean = () => {
  const d = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
  let s = 0;
  for (let i = 0; i < d.length; i += 16) s += d[i] + d[i + 1] + d[i + 2];
  return s / (d.length / 16);
};
const out = [];
let i = 0;
const next = () => {
  if (i >= n) { v.onDrawn = null; done(out); return; }
  const base = mean(), t0 = performance.now();
  slider.value = i % 2 ? -0.5 : 0.5;
  slider.dispatchEvent(new Event('input'));
  v.onDrawn = () => {
    if (Math.abs(mean() - base) < 2) return;
    v.onDrawn = null;
    out.push(performance.now() - t0);
    i++;
    setTimeout(next, 150);
  };
};
next();
"""


def wait(cond, timeout=60):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.1)
    raise SystemExit("bench_browser: timed out")


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().split("\n")[0])
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--seconds", type=float, default=10)
    ap.add_argument("--moves", type=int, default=20)
    a = ap.parse_args()
    mock.SUITE = mock.Suite("bench_browser")
    with mock.Server(os.path.abspath(a.bin), "--http", "127.0.0.1:0", "--scene", "demo") as srv:
        port = next(int(x.rsplit(":", 1)[1]) for x in srv.stdout_lines
                    if x.startswith("volfxd http on "))
        drv = browser.start_chromium()
        try:
            drv.set_script_timeout(300)
            drv.get("http://127.0.0.1:%d/" % port)
            drawn = lambda: drv.execute_script("return window.volfxViewer.framesDrawn")  # noqa
            wait(lambda: drawn() >= 1)
            # A paused, unchanged scene sends its first frame only: play it.
            drv.find_element(By.ID, "play").click()
            wait(lambda: drawn() >= 3)
            rows = []
            for fps in (30, 60):
                box = drv.find_element(By.ID, "fps-target")
                box.clear()
                box.send_keys(str(fps) + "\t")
                time.sleep(2)
                n0, t0 = drawn(), time.monotonic()
                time.sleep(a.seconds)
                rows.append((fps, (drawn() - n0) / (time.monotonic() - t0)))
            drv.find_element(By.ID, "pause").click()
            drv.execute_script("""
                for (const s of document.querySelectorAll('#form > details > summary'))
                  if (s.textContent === 'render') s.parentElement.open = true;""")
            time.sleep(1)
            lat = sorted(drv.execute_async_script(LATENCY_JS, a.moves))
        finally:
            drv.quit()
    print("frames drawn by the page, 640x360 JPEG, demo scene playing:")
    for fps, got in rows:
        print("  requested %2d fps: %.1f fps" % (fps, got))
    p90 = lat[min(len(lat) - 1, int(0.9 * len(lat)))]
    print("slider to frame (exposure, paused scene, %d moves, 30 fps stream): median %.0f ms, "
          "p90 %.0f ms, min %.0f ms, max %.0f ms" % (len(lat), statistics.median(lat), p90,
                                                     lat[0], lat[-1]))


if __name__ == "__main__":
    main()
