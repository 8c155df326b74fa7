"""A stand-alone WSC1 subscriber written from DESIGN.md alone (not from wristscan's decoder).

Usage: python wsc1_subscriber.py ENDPOINT PREFIX OUT.npz SECONDS

Subscribes to ``PREFIX/cloud``, decodes every payload by the documented layout, and saves all
points plus each batch's header fields. Prints one line "ready" once subscribed.
"""

from __future__ import annotations

import json
import struct
import sys
import time

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
    if flags & 2:
        off += 4 * n
    assert off == len(buf), (off, len(buf))
    return {
        "seq": seq,
        "t0": t0,
        "t1": t1,
        "n_profiles": n_prof,
        "frame": frame.rstrip(b"\0").decode(),
        "xyz": xyz,
        "encoding_ok": True,
    }


def main() -> int:
    endpoint, prefix, out, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    batches: list[dict[str, object]] = []
    encodings: set[str] = set()

    def on_sample(sample: zenoh.Sample) -> None:
        encodings.add(str(sample.encoding))
        batches.append(decode(sample.payload.to_bytes()))

    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"{prefix}/cloud", on_sample)
        print("ready", flush=True)
        time.sleep(seconds)
        sub.undeclare()
    xyz = np.concatenate([b["xyz"] for b in batches]) if batches else np.zeros((0, 3))
    np.savez(
        out,
        xyz=xyz,
        seq=np.array([b["seq"] for b in batches], dtype=np.int64),
        t0=np.array([b["t0"] for b in batches], dtype=np.int64),
        n_profiles=np.array([b["n_profiles"] for b in batches], dtype=np.int64),
        frames=np.array([b["frame"] for b in batches]),
        encodings=np.array(sorted(encodings)),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
