#!/usr/bin/env python3
"""Checks a Debian machine-readable copyright file (copyright-format 1.0, DEP-5).

    copyright_check.py FILE

Checks what the format requires and what a reader relies on: the header paragraph starts with
the Format field of version 1.0; every paragraph is "Field: value" lines with indented
continuation lines; a "Files: *" paragraph exists; every Files paragraph has Copyright and
License; every license short name used (split on "or" / "and", "with ... exception" kept) has
its text in a stand-alone License paragraph or in that Files paragraph; a text that points to
/usr/share/common-licenses names a file that exists; no stand-alone License paragraph is unused.
Prints one line per problem and exits 1 when there is any.
"""
import os
import re
import sys

FORMAT = "https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/"
FIELD = re.compile(r"^([A-Za-z][A-Za-z0-9-]*):(.*)$")


def paragraphs(text):
    """[(line number, {field: [first line, continuation lines...]})]"""
    out, current, start, last = [], {}, 0, None
    for number, line in enumerate(text.split("\n"), 1):
        if not line.strip():
            if current:
                out.append((start, current))
            current, last = {}, None
            continue
        if line[0] in " \t":
            if last is None:
                raise ValueError(f"line {number}: continuation line outside a field")
            current[last].append(line.strip())
            continue
        m = FIELD.match(line)
        if not m:
            raise ValueError(f"line {number}: not 'Field: value': {line!r}")
        if not current:
            start = number
        name = m.group(1)
        if name.lower() in (k.lower() for k in current):
            raise ValueError(f"line {number}: field {name} repeated in one paragraph")
        current[name] = [m.group(2).strip()]
        last = name
    if current:
        out.append((start, current))
    return out


def short_names(expression):
    # "GPL-2+ or MPL-2.0", "Expat and BSD-3-clause", "GPL-2+ with OpenSSL exception"
    names = []
    for part in re.split(r"\s+(?:or|and)\s+|,\s*", expression):
        part = part.strip()
        if part:
            names.append(part)
    return names


def main(path):
    problems = []
    try:
        paras = paragraphs(open(path, encoding="utf-8").read())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        print(f"{path}: {e}")
        return 1
    if not paras:
        print(f"{path}: empty")
        return 1
    header_line, header = paras[0]
    if header.get("Format", [""])[0] != FORMAT:
        problems.append(f"line {header_line}: the header's Format is not {FORMAT}")
    files = [(n, p) for n, p in paras[1:] if "Files" in p]
    standalone = {}
    for n, p in paras[1:]:
        if "Files" in p:
            continue
        if "License" not in p:
            problems.append(f"line {n}: a paragraph with neither Files nor License")
            continue
        name = p["License"][0]
        if len(p["License"]) < 2:
            problems.append(f"line {n}: stand-alone License {name} has no text")
        if name in standalone:
            problems.append(f"line {n}: License {name} given twice")
        standalone[name] = p["License"][1:]
    if not any(p["Files"][0] == "*" for _, p in files):
        problems.append("no 'Files: *' paragraph")
    used = set()
    for n, p in files:
        for field in ("Copyright", "License"):
            if field not in p or not " ".join(p[field]).strip():
                problems.append(f"line {n}: Files {p['Files'][0]}: no {field}")
        if "License" not in p:
            continue
        expression, inline_text = p["License"][0], p["License"][1:]
        for name in short_names(expression):
            used.add(name)
            if inline_text:
                continue
            if name not in standalone:
                problems.append(f"line {n}: License {name} has no text (no stand-alone paragraph)")
    for name, text in standalone.items():
        if name not in used:
            problems.append(f"stand-alone License {name} is used by no Files paragraph")
        for ref in re.findall(r"/usr/share/common-licenses/[A-Za-z0-9.+-]*[A-Za-z0-9+-]",
                              " ".join(text)):
            if not os.path.isfile(ref):
                problems.append(f"License {name}: {ref} does not exist")
    for p in problems:
        print(f"{path}: {p}")
    return 1 if problems else 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print(__doc__)
        sys.exit(2)
    sys.exit(main(sys.argv[1]))
