"""A stand-alone WSC1 subscriber written from DESIGN.md alone (not from wristscan's decoder).

Usage: python wsc1_subscriber.py ENDPOINT PREFIX OUT.npz SECONDS

Subscribes to ``PREFIX/cloud``, decodes every payload by the documented layout, and saves all
points plus each batch's header fields, and for every point the UTC time of its profile's
exposure (``point_t``: what tells a forward sweep from the backward one), from the profile index
block when the daemon publishes it (the batch's profiles evenly spread from its first exposure to
its last), else the batch's first exposure. Prints one line
"ready" once subscribed. Stops after SECONDS, or earlier once a line ``stop UTC_NS`` has come on
stdin and a batch whose first exposure is at or after ``UTC_NS`` has arrived (everything exposed
before that instant is in; batches are published in order, empty ones too).
"""

from __future__ import annotations

import json
import struct
import sys
import threading

import numpy as np
import zenoh


def decode(buf: bytes) -> dict[str, object]:
    magic, version, flags, seq, t0, t1, n, n_prof, frame = struct.unpack_from(
        "<4sHHQqqII16s", buf, 0
    )
    assert magic == b"WSC1" and version == 1, (magic, version)
    xyz = np.frombuffer(buf, "<f4", 3 * n, 64).reshape(n, 3)
    off = 64 + 12 * n
    if flags & 1:
        off += n
    t = np.full(n, t0, dtype=np.int64)
    if flags & 2:
        index = np.frombuffer(buf, "<u4", n, off).astype(np.float64)
        t += np.rint((t1 - t0) * index / max(n_prof - 1, 1)).astype(np.int64)
        off += 4 * n
    assert off == len(buf), (off, len(buf))
    return {
        "seq": seq,
        "t0": t0,
        "t1": t1,
        "n_profiles": n_prof,
        "frame": frame.rstrip(b"\0").decode(),
        "xyz": xyz,
        "t": t,
    }


def main() -> int:
    endpoint, prefix, out, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    batches: list[dict[str, object]] = []
    encodings: set[str] = set()
    stop_at = [2**63 - 1]  # UTC ns: done once a batch exposed at or after it has come
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        encodings.add(str(sample.encoding))
        b = decode(sample.payload.to_bytes())
        batches.append(b)
        if int(b["t0"]) >= stop_at[0]:  # type: ignore[call-overload]
            done.set()

    def read_stdin() -> None:
        for line in sys.stdin:
            words = line.split()
            if len(words) == 2 and words[0] == "stop":
                stop_at[0] = int(words[1])
                if batches and int(batches[-1]["t0"]) >= stop_at[0]:  # type: ignore[call-overload]
                    done.set()

    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"{prefix}/cloud", on_sample)
        threading.Thread(target=read_stdin, daemon=True).start()
        print("ready", flush=True)
        done.wait(seconds)
        sub.undeclare()
    xyz = np.concatenate([b["xyz"] for b in batches]) if batches else np.zeros((0, 3))
    np.savez(
        out,
        xyz=xyz,
        point_t=np.concatenate([b["t"] for b in batches]) if batches else np.zeros(0, np.int64),
        seq=np.array([b["seq"] for b in batches], dtype=np.int64),
        t0=np.array([b["t0"] for b in batches], dtype=np.int64),
        n_profiles=np.array([b["n_profiles"] for b in batches], dtype=np.int64),
        frames=np.array([b["frame"] for b in batches]),
        encodings=np.array(sorted(encodings)),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
