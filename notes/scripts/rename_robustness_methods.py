"""Rewrite the method column of a robustness study CSV from the names the committed rows were
written under to today's ``registration.pipeline.METHODS`` names; every other byte stays.

    python notes/scripts/rename_robustness_methods.py results/robustness.csv

Run once on the committed rows (rows written since already carry the new names); a name
that is neither old nor in ``METHODS`` stops it before anything is written.
"""

import argparse
import csv
import io
from pathlib import Path

from navapp.registration.pipeline import METHODS

OLD_TO_NEW = {
    "before": "single-icp",
    "after": "default",
    "first-after": "multistart",
    "after-no-continuation": "default-no-continuation",
    "after-plain-icp": "default-plain-icp",
    "after-continuation": "multistart-continuation-10x",
}


def rename(text: str) -> tuple[str, int]:
    """``text`` (a whole CSV) with the method column renamed, and the number of rows changed."""
    # the CSV module would requote or re-terminate lines: rewrite only the method field
    lines = text.splitlines(keepends=True)
    header = next(csv.reader(io.StringIO(lines[0])))
    col = header.index("method")
    out, changed = [lines[0]], 0
    for line in lines[1:]:
        fields = next(csv.reader(io.StringIO(line)))
        name = fields[col]
        new = OLD_TO_NEW.get(name, name)
        if new not in METHODS:
            raise SystemExit(f"unknown method {name!r} in {line!r}")
        if new != name:
            if '"' in line:
                raise SystemExit(f"quoted field in {line!r}: rewrite it by hand")
            fields[col] = new
            line = ",".join(fields) + line[len(line.rstrip("\r\n")):]
            changed += 1
        out.append(line)
    return "".join(out), changed


def main(paths) -> None:
    for p in map(Path, paths):
        with p.open(newline="") as f:  # keep the file's \r\n (csv.writer's line ending)
            text, changed = rename(f.read())
        with p.open("w", newline="") as f:
            f.write(text)
        print(f"{p}: {changed} rows renamed")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", type=Path, help="robustness study CSVs, rewritten in place")
    args = ap.parse_args()
    for p in args.csv:
        if not p.is_file():
            ap.error(f"{p}: no such file")
    main(args.csv)
