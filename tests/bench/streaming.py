"""
The frame-stream loop the end-to-end benchmarks share: a subscribed client reads `frames`
notifications as fast as the server pushes them.
"""

import time


def receive_frames(c, seconds, timeout=600, on_first=None):
    """
    Reads `frames` notifications from connection 'c' for 'seconds' and skips anything else. The
    clock starts at the first frame, after any warm-up; that frame is not counted, and
    'on_first(params)', when given, is called as it arrives (to read a CPU clock there, say).
    Returns (frames, elapsed): the (params, attachment) of each counted frame, and the seconds
    from the first frame to the end.
    """
    frames, t0 = [], None
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        msg, att = c.recv(timeout=timeout)
        if not isinstance(msg, dict) or msg.get("method") != "frames":
            continue
        if t0 is None:
            t0 = time.perf_counter()
            if on_first:
                on_first(msg["params"])
            continue
        frames.append((msg["params"], att))
    if t0 is None:
        raise SystemExit("no frame arrived in %g s" % seconds)
    return frames, time.perf_counter() - t0
