#!/usr/bin/env python3
"""Checks that moving the README's reference into docs/ lost nothing (issue 23, part 6).

Run from the repository root (manual check; CI does not run it, it needs git history):

    python3 tests/docs_check.py [OLD_README]

OLD_README defaults to the README.md of commit 38b3fac (the last one with the whole
reference in one page), read with `git show`. It checks, against README.md + docs/*.md:

1. every heading (`#`, `##`, `###`, ...) of the old README appears as a heading (any
   level: a section may have become a page title);
2. every line inside a fenced code block of the old README appears inside a fenced code
   block of the new files (examples, schemas, logs);
3. every bold lead-in (`**sensor.toml**`, `**Plan caps.**`, ...) and the first cell of
   every table row appear; a command row (`` `tactbench ...` ``) also counts as kept
   when its command is there with options added since in `[...]` groups (`run --resume
   DIR [--limit N]`), printed as "kept, with options added since" for review;
4. every relative link in README.md and docs/*.md points to a file that exists, except
   the feature pages other branches add (listed as pending);

and reports how many non-blank lines of the old README appear verbatim (the rest were
rewritten cross-references: printed for review). Exit 0 when 1-4 hold, else 1.
"""

import glob
import os
import re
import subprocess
import sys

OLD_REV = "38b3fac"
# Pages written on other branches of this release (linked from docs/README.md).
PENDING = {
    "docs/real-sensors.md", "docs/tracking.md", "docs/limits.md", "docs/force-sensors.md",
    "docs/marlin.md", "docs/live-view.md", "docs/run-record.md",
}


def code_lines(lines):
    out, inside = [], False
    for line in lines:
        if line.lstrip().startswith("```"):
            inside = not inside
            continue
        if inside and line.strip():
            out.append(line.strip())
    return out


def headings(lines):
    out, inside = [], False
    for line in lines:
        if line.lstrip().startswith("```"):
            inside = not inside
        elif not inside and re.match(r"^#{1,6} ", line):
            out.append(line.lstrip("#").strip())
    return out


def bold_leads(lines):
    return [m.group(1) for l in lines for m in [re.match(r"^\*\*([^*]+)\*\*", l)] if m]


def without_added_options(new_cell, old_cell):
    """The options `new_cell` adds to the command `old_cell`, or None when it is not that
    command: a command row's first cell (`` `tactbench ...` ``) is kept when removing
    some of the new cell's top-level `[...]` groups (options added since, such as
    `[--limit N]`) gives back the old cell, word for word."""
    code = [c for c in (new_cell, old_cell) if c.startswith("`tactbench ") and c.endswith("`")]
    if len(code) != 2:
        return None
    new_cell, old_cell = new_cell[1:-1], old_cell[1:-1]
    # The new cell's top-level parts: bracketed groups and the words between them.
    parts, depth, cur = [], 0, ""
    for ch in new_cell:
        if ch == "[" and depth == 0:
            if cur.strip():
                parts.append(("text", cur.split()))
            cur = ch
            depth = 1
        elif ch == "[":
            cur += ch
            depth += 1
        elif ch == "]" and depth == 1:
            parts.append(("group", cur + ch))
            cur, depth = "", 0
        else:
            cur += ch
            if ch == "]":
                depth -= 1
    if depth != 0:
        return None
    if cur.strip():
        parts.append(("text", cur.split()))
    # Match the old cell's words: every text word in order, each group either
    # matched whole or counted as added.
    words = old_cell.split()
    i, added = 0, []
    for kind, part in parts:
        if kind == "text":
            if words[i:i + len(part)] != part:
                return None
            i += len(part)
        else:
            g = part.split()
            if words[i:i + len(g)] == g:
                i += len(g)
            else:
                added.append(part)
    return added if i == len(words) and added else None


def with_added_items(new_cell, old_cell):
    """The items `new_cell` adds to the list `old_cell`, or None: a first cell that lists
    names (`` `a`, `b`, `c` ``) is kept when the new cell lists every old name in the
    same order with names added (metrics added since, such as `run.failed_rows`)."""
    split = lambda c: [x.strip() for x in c.split(",")]
    old, new = split(old_cell), split(new_cell)
    if len(old) < 2 or not all(x.startswith("`") and x.endswith("`") for x in old + new):
        return None
    it = iter(new)
    if not all(any(o == n for n in it) for o in old):
        return None
    added = [n for n in new if n not in old]
    return added or None


def table_first_cells(lines):
    out = []
    for l in lines:
        if l.startswith("|") and not re.match(r"^\|[-| :]+\|$", l):
            out.append(l.split("|")[1].strip())
    return out


def main():
    if len(sys.argv) > 1:
        old = open(sys.argv[1], encoding="utf-8").read().split("\n")
    else:
        old = subprocess.run(["git", "show", f"{OLD_REV}:README.md"], check=True,
                             capture_output=True, text=True).stdout.split("\n")
    files = ["README.md"] + sorted(glob.glob("docs/*.md"))
    new = {f: open(f, encoding="utf-8").read().split("\n") for f in files}
    all_new = [l for ls in new.values() for l in ls]
    text_new = "\n".join(all_new)

    failures = []
    new_headings = set(headings(all_new))
    for h in headings(old):
        if h not in new_headings:
            failures.append(f"heading lost: {h}")
    new_code = set()
    for ls in new.values():
        new_code.update(code_lines(ls))
    old_code = code_lines(old)
    for l in old_code:
        if l not in new_code:
            failures.append(f"code-block line lost: {l}")
    for b in bold_leads(old):
        if f"**{b}**" not in text_new:
            failures.append(f"bold lead-in lost: **{b}**")
    new_cells = table_first_cells(all_new)
    widened = []
    for c in table_first_cells(old):
        if c in new_cells:
            continue
        grown = [
            (n, a)
            for n in new_cells
            for a in [without_added_options(n, c) or with_added_items(n, c)]
            if a
        ]
        if grown:
            widened.append((c, grown[0][1]))
        else:
            failures.append(f"table row lost: | {c} |")

    pending = set()
    for f, ls in new.items():
        base = os.path.dirname(f)
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", "\n".join(ls)):
            if re.match(r"^[a-z]+:", target):
                continue
            path = os.path.normpath(os.path.join(base, target))
            if path in PENDING and not os.path.exists(path):
                pending.add(path)
            elif not os.path.exists(path):
                failures.append(f"{f}: broken link {target}")

    new_set = set(l.rstrip() for l in all_new)
    old_text = [l.rstrip() for l in old if l.strip()]
    missing = [l for l in old_text if l not in new_set]
    print(f"old README: {len(old)} lines, {len(headings(old))} headings, {len(old_code)} "
          f"code-block lines, {len(bold_leads(old))} bold lead-ins, "
          f"{len(table_first_cells(old))} table rows")
    print(f"new: README.md {len(new['README.md'])} lines + {len(files) - 1} pages in docs/ "
          f"({sum(len(v) for k, v in new.items() if k != 'README.md')} lines)")
    print(f"verbatim: {len(old_text) - len(missing)} of {len(old_text)} non-blank old lines; "
          f"rewritten ({len(missing)}):")
    for l in missing:
        print(f"  ~ {l}")
    for c, added in widened:
        print(f"kept, with options or items added since: | {c} | + {' '.join(added)}")
    for p in sorted(pending):
        print(f"pending (added by another branch of this release): {p}")
    for fl in failures:
        print(f"FAIL {fl}")
    print("ok: nothing documented was lost" if not failures else f"{len(failures)} failures")
    return 0 if not failures else 1


if __name__ == "__main__":
    sys.exit(main())
