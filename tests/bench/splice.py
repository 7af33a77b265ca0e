#!/usr/bin/env python3
"""Replace one generated section of BENCHMARKS.md with a new body.

Usage: splice.py NAME BODY_FILE [--file BENCHMARKS.md]

A section is the text between the marker lines `<!-- bench:NAME -->` and
`<!-- /bench:NAME -->`. Each benchmark script writes only its own section, so hand-written
prose around the sections survives `make bench`, and scripts can run in any order or alone.
A section not yet in the file is appended at its end. The file is replaced atomically.
"""
import argparse
import os
import sys
import tempfile


def splice(text: str, name: str, body: str) -> str:
    start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    i = text.find(start)
    if i < 0:
        return text.rstrip() + "\n\n" + block + "\n"
    j = text.find(end, i)
    if j < 0:
        sys.exit(f"splice.py: {start} has no closing {end}")
    return text[:i] + block + text[j + len(end):]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name")
    parser.add_argument("body_file")
    parser.add_argument("--file", default="BENCHMARKS.md")
    args = parser.parse_args()
    if not args.name.replace("-", "").replace("_", "").isalnum():
        sys.exit(f"splice.py: section name {args.name!r} must be letters, digits, - or _")
    with open(args.body_file, encoding="utf-8") as f:
        body = f.read()
    with open(args.file, encoding="utf-8") as f:
        text = f.read()
    out = splice(text, args.name, body)
    directory = os.path.dirname(os.path.abspath(args.file))
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".benchmarks.")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(out)
    os.replace(tmp, args.file)


if __name__ == "__main__":
    main()
