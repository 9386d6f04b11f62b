#!/usr/bin/env python3
"""
The browser viewer in a real browser: headless Chromium (through selenium and chromedriver)
loads the page volfxd --http serves and uses it as a person would.

- Without a token, and with a wrong one, the page says it is not authorized; the right token
  connects.
- Frames arrive, and the picture changes as the scene plays; the frame counter moves.
- Moving the exposure slider (keyboard on the range input) changes the frame, and the value
  reads back over TCP with scene.get.
- A value the server refuses (a negative light intensity) shows the server's message beside
  that field, and the stream goes on.
- Scenes are created from a preset and deleted from the page.

With --screenshots DIR it also saves the page's screenshots there (docs/images/).

    python3 tests/browser/test_viewer.py --bin build/bin
"""

import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import browser  # noqa: E402

browser.ensure_selenium()
browser.find_chromium()

import mock  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

suite = mock.Suite("test_viewer", timeout_s=400)
T = suite.test
TOKEN = "open-sesame"


def http_port(srv):
    for line in srv.stdout_lines:
        if line.startswith("volfxd http on "):
            return int(line.rsplit(":", 1)[1])
    raise mock.CheckError("volfxd printed no 'volfxd http on HOST:PORT' line")


def wait(what, cond, timeout=30.0, step=0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(step)
    raise mock.CheckError("timed out after %.0f s waiting for %s" % (timeout, what))


def text(drv, id_):
    return drv.find_element(By.ID, id_).text


def frames_drawn(drv):
    return drv.execute_script("return window.volfxViewer.framesDrawn")


def field_input(drv, path, kind):
    return drv.find_element(By.CSS_SELECTOR, 'input[type=%s][data-path="%s"]' % (kind, path))


def open_section(drv, name):
    drv.execute_script("""
        for (const s of document.querySelectorAll('#form > details > summary'))
          if (s.textContent === arguments[0]) s.parentElement.open = true;""", name)


def browser_log(drv):
    try:
        return "\n".join(e["message"] for e in drv.get_log("browser"))
    except Exception:  # noqa: BLE001
        return ""


@T
def viewer(s):
    shots = suite.args.screenshots and os.path.abspath(suite.args.screenshots)
    if shots:
        os.makedirs(shots, exist_ok=True)
    with mock.Server(suite.bin, "--token", TOKEN, "--http", "127.0.0.1:0") as srv:
        port = http_port(srv)
        drv = browser.start_chromium()
        try:
            run(drv, srv, port, shots)
        except Exception:
            print(browser_log(drv))
            raise
        finally:
            drv.quit()


def run(drv, srv, port, shots):
    url = "http://127.0.0.1:%d/" % port
    # No token: refused, and said so beside the token field.
    drv.get(url)
    wait("the page's refusal without a token", lambda: text(drv, "token-error"))
    suite.check("unauthorized" in text(drv, "token-error"), "without a token: unauthorized",
                text(drv, "token-error"))
    # A wrong token: refused.
    tok = drv.find_element(By.ID, "token")
    tok.send_keys("not-the-token")
    drv.find_element(By.ID, "connect").click()
    wait("the wrong token's refusal", lambda: "wrong token" in text(drv, "token-error"))
    suite.check("not authorized" in text(drv, "status"), "the status says not authorized",
                text(drv, "status"))
    suite.eq(frames_drawn(drv), 0, "no frame without the token")
    # The right token.
    tok.clear()
    tok.send_keys(TOKEN + Keys.ENTER)
    wait("connected", lambda: "connected" in text(drv, "status") and
         "not" not in text(drv, "status"))
    suite.eq(text(drv, "token-error"), "", "no token error once connected")
    wait("the first frames", lambda: frames_drawn(drv) >= 3)
    still = browser.canvas_digest(drv)
    suite.check(still[1] > 3, "the frame is not black", still)

    # Play: the picture and the frame counter change.
    drv.find_element(By.ID, "play").click()
    wait("the scene to play", lambda: int(text(drv, "frame")) > 5)
    moving = wait("the picture to change as the scene plays",
                  lambda: (lambda d: d if d[0] != still[0] else None)(browser.canvas_digest(drv)))
    time.sleep(0.5)
    suite.check(browser.canvas_digest(drv)[0] != moving[0], "it keeps changing while playing")
    wait("the fps counter", lambda: int(text(drv, "fps")) > 0)
    suite.check(int(text(drv, "rate")) > 0, "bytes a second are shown", text(drv, "rate"))
    suite.check(text(drv, "work") not in ("", "–"), "the render time is shown", text(drv, "work"))
    if shots:
        drv.save_screenshot(os.path.join(shots, "viewer.png"))
    drv.find_element(By.ID, "pause").click()
    time.sleep(0.6)
    f0 = int(text(drv, "frame"))
    drv.find_element(By.ID, "step").click()
    wait("a step", lambda: int(text(drv, "frame")) == f0 + 1)

    # The exposure slider: the frame changes and the value reads back over TCP.
    open_section(drv, "render")
    before = browser.canvas_digest(drv)
    slider = field_input(drv, "render.exposure", "range")
    drv.execute_script("arguments[0].scrollIntoView({block: 'center'})", slider)
    slider.click()
    for _ in range(40):
        slider.send_keys(Keys.ARROW_RIGHT)
    wanted = float(slider.get_attribute("value"))
    suite.check(wanted > 0, "the slider moved", wanted)
    with mock.Conn(srv.host, srv.port) as c:
        c.call("auth", {"token": TOKEN})

        def exposure():
            r, _ = c.call("scene.get", {})
            return r["result"]["render"]["exposure"]
        wait("the exposure to reach the scene", lambda: abs(exposure() - wanted) < 1e-6)
    after = wait("a brighter frame",
                 lambda: (lambda d: d if d[1] > before[1] + 2 else None)(browser.canvas_digest(drv)))
    suite.check(after[0] != before[0], "the frame changed with the slider")

    # A value the server refuses: its message beside the field.
    open_section(drv, "light")
    box = field_input(drv, "light.intensity", "number")
    drv.execute_script("arguments[0].scrollIntoView({block: 'center'})", box)
    box.clear()
    box.send_keys("-5" + Keys.TAB)
    err = drv.find_element(By.CSS_SELECTOR, '[data-error-for="light.intensity"]')
    wait("the refusal beside the field", lambda: err.text)
    suite.check("light.intensity" in err.text and "-32602" not in err.text,
                "the server's message names the field", err.text)
    suite.check("bad" in box.get_attribute("class"), "the field is marked")
    if shots:
        drv.save_screenshot(os.path.join(shots, "viewer-error.png"))
    n = frames_drawn(drv)
    wait("frames after the refusal", lambda: frames_drawn(drv) > n + 2)

    # Orbit: dragging the view changes this viewer's picture, not the scene's camera.
    from selenium.webdriver.common.action_chains import ActionChains
    canvas = drv.find_element(By.ID, "view")
    d0 = browser.canvas_digest(drv)
    ActionChains(drv).move_to_element(canvas).click_and_hold().move_by_offset(120, 30) \
        .release().perform()
    wait("the orbited view", lambda: browser.canvas_digest(drv)[0] != d0[0])
    with mock.Conn(srv.host, srv.port) as c:
        c.call("auth", {"token": TOKEN})
        r, _ = c.call("scene.get", {})
        suite.eq(r["result"]["camera"]["eye"], [0, 2.2, 7.5], "the scene's camera is unchanged")

    # Scenes: create from a preset, then delete.
    drv.find_element(By.ID, "create-name").send_keys("second")
    from selenium.webdriver.support.ui import Select
    Select(drv.find_element(By.ID, "preset")).select_by_value("demo")
    drv.find_element(By.ID, "create").click()
    wait("the new scene listed and shown",
         lambda: drv.find_elements(By.CSS_SELECTOR, '#scene-list li.current[data-scene="second"]'))
    n = frames_drawn(drv)
    wait("frames of the new scene", lambda: frames_drawn(drv) > n + 2)
    drv.find_element(By.ID, "delete").click()
    wait("the scene gone",
         lambda: not drv.find_elements(By.CSS_SELECTOR, '#scene-list li[data-scene="second"]'))
    suite.eq(text(drv, "scene-error"), "", "no scene error")


suite.main(lambda ap: ap.add_argument("--screenshots", metavar="DIR",
                                     help="also save the page's screenshots in DIR"))
