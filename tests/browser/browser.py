"""
Headless Chromium for the viewer's tests and benchmark: finds an interpreter with selenium
(re-running the calling script with it when the current one lacks it), starts Chromium through
chromedriver, and reads the viewer's canvas. A machine without Chromium, chromedriver or
selenium makes the caller exit 77 (skipped); run.sh installs all three.
"""

import os
import shutil
import subprocess
import sys

SKIP = 77
CANDIDATES = ("/usr/bin/python3", "/usr/local/bin/python3")


def ensure_selenium():
    """Returns once selenium imports, re-executing this script with another Python if need be;
    exits 77 when no Python here has it."""
    try:
        import selenium  # noqa: F401
        return
    except ImportError:
        pass
    if os.environ.get("VOLFX_BROWSER_REEXEC"):
        print("selenium is not installed (Debian: python3-selenium): skipped")
        sys.exit(SKIP)
    for py in CANDIDATES:
        if os.path.exists(py) and os.path.realpath(py) != os.path.realpath(sys.executable) and \
                subprocess.run([py, "-c", "import selenium"], capture_output=True).returncode == 0:
            env = dict(os.environ, VOLFX_BROWSER_REEXEC="1")
            os.execve(py, [py] + sys.argv, env)
    print("selenium is not installed (Debian: python3-selenium): skipped")
    sys.exit(SKIP)


def find_chromium():
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or \
        shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    if not browser or not driver:
        print("Chromium or chromedriver is missing (Debian: chromium, chromium-driver): skipped")
        sys.exit(SKIP)
    return browser, driver


def start_chromium(width=1500, height=940):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    browser, driver = find_chromium()
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=%d,%d" % (width, height), "--force-device-scale-factor=1",
              "--no-first-run", "--disable-extensions", "--disable-background-networking"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(executable_path=driver), options=opts)


def canvas_digest(drv):
    """A hash of the viewer's canvas pixels, and their mean brightness (0-255)."""
    return drv.execute_script("""
        const c = document.getElementById('view');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let h = 2166136261, sum = 0;
        for (let i = 0; i < d.length; i++) {
          h = Math.imul(h ^ d[i], 16777619) >>> 0;
          if ((i & 3) !== 3) sum += d[i];
        }
        return [h.toString(16), sum / (d.length / 4) / 3];
    """)
