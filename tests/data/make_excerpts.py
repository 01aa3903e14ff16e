"""Recreate the real-data excerpts in tests/data from the shared recordings.

Run from the repository root: ``python tests/data/make_excerpts.py`` (needs ../shared/data).
"""

from __future__ import annotations

import gzip
from pathlib import Path

from rosbags.rosbag1 import Reader, Writer

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[2] / "shared" / "data"


def carmen_excerpt(n_laser: int = 100) -> None:
    src = SHARED / "carmen" / "intel-corrected.log.gz"
    out: list[str] = []
    seen = 0
    with gzip.open(src, "rt") as fh:
        for line in fh:
            out.append(line)
            if line.startswith("FLASER"):
                seen += 1
                if seen == n_laser:
                    break
    dest = HERE / "intel-corrected-excerpt.log.gz"
    # mtime=0: the bytes do not depend on when the excerpt was made
    with open(dest, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
        gz.write("".join(out).encode())


def bag_excerpt(n_scans: int = 60) -> None:
    src = SHARED / "rosbag" / "ccny_laser_scan_matcher_demo.bag"
    dest = HERE / "ccny-excerpt.bag"
    dest.unlink(missing_ok=True)
    with Reader(src) as reader, Writer(dest) as writer:
        conns = {}
        for c in reader.connections:
            conns[c.id] = writer.add_connection(
                c.topic,
                c.msgtype,
                msgdef=c.msgdef.data,
                md5sum=c.digest,
                callerid=c.ext.callerid,
                latching=c.ext.latching,
            )
        count = 0
        for c, t, raw in reader.messages():
            writer.write(conns[c.id], t, raw)
            if c.msgtype.endswith("LaserScan"):
                count += 1
                if count == n_scans:
                    break


if __name__ == "__main__":
    carmen_excerpt()
    bag_excerpt()
