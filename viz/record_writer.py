"""The recording writer process (see viz/record.py): imports rerun-sdk at once, then writes each recording the
parent sends (length-prefixed pickles of Recorder calls on stdin), answering one line per recording."""
from __future__ import annotations

import signal
import sys


def main() -> int:
    # Ctrl-C is the parent's to handle; this process ends when the parent closes the pipe
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import pickle

    import rerun  # noqa: F401  (the reason this process exists: loaded while the parent works)

    from wrenorm.viz.record import replay

    inp, out = sys.stdin.buffer, sys.stdout
    while True:
        head = inp.read(8)
        if len(head) < 8:
            return 0
        job = pickle.loads(inp.read(int.from_bytes(head, "little")))
        try:
            replay(tuple(job["args"]), job["calls"])
            out.write("ok\n")
        except Exception as e:  # noqa: BLE001  (reported to the parent, which then writes it itself)
            out.write(f"error: {type(e).__name__}: {e}".replace("\n", " ") + "\n")
        out.flush()


if __name__ == "__main__":
    sys.exit(main())
