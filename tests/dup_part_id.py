#!/usr/bin/env python3
"""Hostile per-rank checkpoint for tests/dist_mpm_test.sh: copies the checkpoint directory SRC to
DST and gives the first particle of part 1 the id of part 0's first particle, then makes part 1's
own checksum and the manifest's size and checksum of it consistent again, so that only the
cross-part id check (MpmSimulation::check_slice_ids) can find the repeat.
Usage: dup_part_id.py SRC DST"""
import json
import os
import shutil
import struct
import sys

MAGIC = b"AMALGAM-CKPT\n"


def fnv1a64(data):  # core/hash.hpp
    h = 0xCBF29CE484222325
    for byte in data:
        h = ((h ^ byte) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def id_offset(b):
    """Byte offset of the 'id' attribute's first value in a part file."""
    assert b.startswith(MAGIC), "not an Amalgam checkpoint part"
    pos = len(MAGIC) + 4 + 4 + 8 + 8 + 8 + 4 + 4  # version, real size, fingerprint, time, steps, frame, retries
    (n,) = struct.unpack_from("<Q", b, pos)
    pos += 8
    (nattr,) = struct.unpack_from("<I", b, pos)
    pos += 4
    for _ in range(nattr):
        (length,) = struct.unpack_from("<I", b, pos)
        name = b[pos + 4 : pos + 4 + length].decode()
        pos += 4 + length
        _type, _width, words = struct.unpack_from("<III", b, pos)
        pos += 12
        if name == "id":
            return pos
        pos += n * 4 * words
    raise SystemExit("no id attribute")


src, dst = sys.argv[1], sys.argv[2]
shutil.rmtree(dst, ignore_errors=True)
shutil.copytree(src, dst)
manifest_path = os.path.join(dst, "checkpoint.amck")
manifest = json.load(open(manifest_path))
parts = {p["rank"]: p for p in manifest["parts"]}
b0 = open(os.path.join(dst, parts[0]["file"]), "rb").read()
b1 = bytearray(open(os.path.join(dst, parts[1]["file"]), "rb").read())
(id0,) = struct.unpack_from("<i", b0, id_offset(b0))
struct.pack_into("<i", b1, id_offset(bytes(b1)), id0)
struct.pack_into("<Q", b1, len(b1) - 8, fnv1a64(b1[:-8]))
open(os.path.join(dst, parts[1]["file"]), "wb").write(b1)
parts[1]["bytes"] = len(b1)
parts[1]["fnv1a64"] = "%016x" % fnv1a64(b1)
json.dump(manifest, open(manifest_path, "w"), indent=1)
print("part 1's first particle now has id %d, as part 0's" % id0)
