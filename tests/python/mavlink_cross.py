#!/usr/bin/env python3
"""Cross-checks cooploc's Rust MAVLink frames against pymavlink, an independent implementation.

Usage: mavlink_cross.py DIALECT_XML CASES_JSON
Generates pymavlink bindings from DIALECT_XML with mavgen (wire protocol 2.0), then for every
case {"name", "sysid", "compid", "seq", "fields", "hex"} of CASES_JSON:
  - decodes the Rust-encoded frame "hex" and checks every field equals "fields";
  - encodes "fields" with pymavlink (same header) and reports the frame's hex.
Prints one JSON object: {"cases": [{"name", "decoded_equal", "mismatches", "python_hex"}]}.
"""
import atexit
import contextlib
import json
import math
import os
import sys
import shutil
import tempfile

from pymavlink.generator import mavgen


def load_dialect(xml_path):
    out_dir = tempfile.mkdtemp(prefix="cooploc-mavgen-")
    atexit.register(shutil.rmtree, out_dir, ignore_errors=True)
    opts = mavgen.Opts(os.path.join(out_dir, "cooploc_dialect.py"), wire_protocol="2.0", language="Python3", validate=True)
    with contextlib.redirect_stdout(sys.stderr):  # mavgen reports progress on stdout
        ok = mavgen.mavgen(opts, [xml_path])
    if not ok:
        raise SystemExit("mavgen rejected " + xml_path)
    sys.path.insert(0, out_dir)
    import cooploc_dialect  # noqa: E402

    return cooploc_dialect


def same(a, b):
    if isinstance(a, (list, tuple, bytes, bytearray)):
        a, b = list(a), list(b)
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        if math.isnan(a) and math.isnan(b):
            return True
        return float(a) == float(b)
    return a == b


def main():
    dialect = load_dialect(sys.argv[1])
    with open(sys.argv[2]) as f:
        cases = json.load(f)
    results = []
    for case in cases:
        mav = dialect.MAVLink(None, srcSystem=case["sysid"], srcComponent=case["compid"])
        mav.robust_parsing = False
        msgs = mav.parse_buffer(bytes.fromhex(case["hex"])) or []
        mismatches = []
        if len(msgs) != 1 or msgs[0].get_type() != case["name"]:
            mismatches.append("decoded %r" % [m.get_type() for m in msgs])
        else:
            got = msgs[0]
            for field, want in case["fields"].items():
                have = getattr(got, field)
                if not same(have, want):
                    mismatches.append("%s: pymavlink %r, rust %r" % (field, have, want))
        cls = getattr(dialect, "MAVLink_" + case["name"].lower() + "_message")
        args = [case["fields"][name] for name in cls.fieldnames]
        msg = cls(*args)
        mav.seq = case["seq"]
        packed = msg.pack(mav)
        results.append({"name": case["name"], "decoded_equal": not mismatches, "mismatches": mismatches, "python_hex": packed.hex()})
    json.dump({"cases": results}, sys.stdout)


if __name__ == "__main__":
    main()
