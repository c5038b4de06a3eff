"""A stand-in for train.py in the study's manager tests: serves its trainer.port, records its command line
in the run directory, and ends as the test asks (a file ``finish`` beside the run: exit 0; ``crash``: exit 1;
SIGTERM: saves a fake checkpoint and exits 0)."""

from __future__ import annotations

import json
import signal
import socket
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv if "=" in a)
    run = Path((args.get("resume") or args["hydra.run.dir"]).strip("'"))
    run.mkdir(parents=True, exist_ok=True)
    with open(run / "argv.jsonl", "a") as f:
        f.write(json.dumps(argv) + "\n")
    (run / "config.yaml").write_text("fake: true\n")
    (run / "checkpoints").mkdir(exist_ok=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"fake")
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", int(args["trainer.port"])))
    server.listen()
    server.settimeout(0.05)
    while not stop:
        if (run.parent / "finish").exists():
            (run / "teaching_summary.json").write_text(json.dumps({"presses": 3}))
            return 0
        if (run.parent / "crash").exists():
            return 1
        try:
            server.accept()[0].close()
        except TimeoutError:
            time.sleep(0.01)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
