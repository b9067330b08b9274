#!/usr/bin/env python3
"""Functions in src/ longer than a threshold (issue 32: none over ~150 lines).

A function's length is counted from its `fn` line to the closing brace at the `fn`'s
own indentation (rustfmt's layout), both included; doc comments and attributes above
it are not counted. Nested functions are listed on their own as well.

Run from the repository root (a manual check; docs/status.md lists what it prints):

    python3 tests/fn_lengths.py            # functions over 150 lines in src/
    python3 tests/fn_lengths.py 100        # over 100 lines
    python3 tests/fn_lengths.py 60 src/vision/window.rs
"""
import os
import re
import sys

FN = re.compile(
    r'^(\s*)(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?(extern\s+"C"\s+)?fn\s+(\w+)'
)


def rust_files(root):
    if root.endswith(".rs"):
        return [root]
    return sorted(
        os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs if f.endswith(".rs")
    )


def long_functions(path, threshold):
    lines = open(path, encoding="utf-8").read().split("\n")
    out = []
    for i, line in enumerate(lines):
        m = FN.match(line)
        if not m:
            continue
        indent = m.group(1)
        # The signature may span lines: find its body's opening brace, or a `;`
        # (a declaration without a body, in a trait).
        j = i
        while j < len(lines) and "{" not in lines[j] and not lines[j].rstrip().endswith(";"):
            j += 1
        if j == len(lines) or ("{" not in lines[j]):
            continue
        for k in range(j, len(lines)):
            one_line = k == j and lines[k].count("{") == lines[k].count("}")
            if lines[k] == indent + "}" or one_line:
                if k - i + 1 > threshold:
                    out.append((k - i + 1, path, i + 1, m.group(8)))
                break
    return out


def main():
    threshold = int(sys.argv[1]) if len(sys.argv) > 1 else 150
    root = sys.argv[2] if len(sys.argv) > 2 else "src"
    found = [f for p in rust_files(root) for f in long_functions(p, threshold)]
    for n, path, line, name in sorted(found, reverse=True):
        print(f"{n:5d}  {path}:{line}  {name}")


if __name__ == "__main__":
    main()
