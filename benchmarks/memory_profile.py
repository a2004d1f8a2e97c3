"""Peak memory of one crossline command, by the function running when it was reached.

Runs ``crossline <args>`` in this process (as the console script does) while a thread samples
the resident memory (VmRSS) and the main thread's crossline stack every 50 ms; prints the
highest RSS seen under each stack (its innermost three crossline functions) and the
process's VmHWM. Sampling can miss a spike shorter than 50 ms; VmHWM cannot.

Usage: python benchmarks/memory_profile.py fuse POINTS --out OUT.ply ...   (any crossline command)
Used for benchmarks/results/scale_notes.txt (where a long scan's fuse peaks).
"""

from __future__ import annotations

import sys
import threading
import time

from crossline.cli import main as crossline_main


def _status(key: str) -> float:
    """A /proc/self/status figure in MB (VmRSS, VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main(argv: list[str]) -> int:
    main_id = threading.get_ident()
    peaks: dict[str, tuple[float, str]] = {}
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            frame = sys._current_frames().get(main_id)
            names = []
            while frame is not None:
                path = frame.f_code.co_filename
                if "/crossline/" in path:
                    names.append(f"{path.split('/crossline/')[1]}:{frame.f_code.co_name}")
                frame = frame.f_back
            key = " < ".join(names[:3]) or "(outside crossline)"
            rss = _status("VmRSS")
            if rss > peaks.get(key, (0.0, ""))[0]:
                peaks[key] = (rss, time.strftime("%H:%M:%S"))
            done.wait(0.05)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    t0 = time.perf_counter()
    try:
        rc = crossline_main(argv)
    finally:
        done.set()
        thread.join()
        print(f"--- {time.perf_counter() - t0:.0f} s; VmHWM {_status('VmHWM'):.0f} MB; "
              "highest RSS per stack (MB, when first reached):")
        for key, (rss, when) in sorted(peaks.items(), key=lambda kv: -kv[1][0])[:25]:
            print(f"{rss:8.0f} {when} {key}")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
