#!/usr/bin/env python3
"""Every system file the build used and every program the tests and the demo run must come from
a Debian package that deploy/setup-deps.sh installs (issue 18: a hand-installed package once hid
a missing entry, and a fresh machine could not build).

Inputs, all read from a configured Release build tree (Ninja; the Makefile generator's
depend files are read too):
  - headers: `ninja -t deps` (the compiler's own dependency output, every object);
  - CMake files read at configure time (find_package configs, modules): build.ninja's
    re-run rule;
  - libraries on the link lines (absolute paths and -lNAME, resolved as the compiler does);
  - FILEPATH entries and the config file under each *_DIR entry of CMakeCache.txt;
  - the shared libraries magcal and magcald load (ldd);
  - programs: the build's and the test runner's tools, those the tests and demo start
    (found in their sources: spawn({"X", run({"X", need_tool X, command -v X, "/usr/bin/X",
    pg_tool("X")), resolved on PATH as the tests resolve them (PostgreSQL's server programs
    in `pg_config --bindir`);
  - the modules the tests' Python scripts import, as Debian's /usr/bin/python3 finds them.
Each regular file is mapped to its owning package with `dpkg -S` (directories belong to many
packages and are skipped). An owner is allowed when it is named by `setup-deps.sh --list
--tests`, is a dependency (Depends/PreDepends, recursively: `apt-cache depends --recurse`) of
one that is, or has Priority `required` (a minimal Debian has those). A file no package owns
(/usr/local, a pyenv shim) is an error too: a fresh machine would not have it.

Self-check: the same check with one named package removed from a copy of the list (by default
prometheus-cpp-dev, then python3-yaml) must fail and name that package; otherwise this test
could not fail.

Exit 0: all allowed and every self-check failed as it should; 1: otherwise (each offending
package named with one file or program it provides).
"""

import argparse
import glob
import os
import re
import shutil
import subprocess
import sys

# Tools the build, the test runner and deploy/run-*.sh run by name (CMake finds some of them
# itself: those show up in CMakeCache.txt as well).
DECLARED_PROGRAMS = [
    "bash", "cmake", "ctest", "cpack", "ninja", "ccache", "c++", "cc", "pkg-config", "lcm-gen",
    "dpkg", "dpkg-deb", "dpkg-shlibdeps", "apt-get", "apt-cache", "dpkg-query", "sed", "awk",
    "grep", "cut", "tr", "mktemp", "timeout", "/usr/bin/python3", "chromium",
]

# Source patterns that name a program a test or the demo starts.
PROGRAM_PATTERNS = [
    re.compile(r'(?:spawn|run)\(\{\s*"([A-Za-z0-9_.+-]+)"'),
    re.compile(r'\bneed_tool\s+"?([A-Za-z0-9_.+-]+)'),
    re.compile(r'command -v\s+"?([A-Za-z0-9_.+-]+)'),
    re.compile(r'"(/usr/s?bin/[A-Za-z0-9_.+-]+)"'),
    re.compile(r'\bpg_tool\("([A-Za-z0-9_.+-]+)"'),
]
SOURCE_GLOBS = ["tests/**/*.cpp", "tests/**/*.hpp", "tests/**/*.sh", "deploy/*.sh"]
# Python modules the tests' scripts import (run by Debian's /usr/bin/python3).
MODULE_PATTERN = re.compile(r"^\s*(?:import|from)\s+([A-Za-z_][A-Za-z0-9_]*)", re.M)


def run(cmd, check=True, **kwargs):
    return subprocess.run(cmd, check=check, text=True, capture_output=True, **kwargs)


def outside(path, roots):
    real = os.path.realpath(path)
    return not any(real == r or real.startswith(r + os.sep) for r in roots)


def build_files(build_dir, roots):
    """Absolute paths of system files the build read or linked, with what used them."""
    files = {}

    def add(path, why):
        if path.startswith("/") and outside(path, roots) and os.path.exists(path):
            if not os.path.isdir(path):
                files.setdefault(os.path.normpath(path), why)

    ninja_file = os.path.join(build_dir, "build.ninja")
    if os.path.exists(ninja_file):
        deps = run(["ninja", "-C", build_dir, "-t", "deps"]).stdout
        for line in deps.splitlines():
            if line.startswith("    "):
                add(line.strip(), "a compiled source includes it (ninja -t deps)")
        text = open(ninja_file, encoding="utf-8", errors="replace").read()
        # The re-run rule lists every CMake file configure read.
        for m in re.finditer(r"^build build\.ninja[^\n]*?: RERUN_CMAKE[^|\n]*\|((?:[^\n]|\$\n)*)",
                             text, re.M):
            for token in re.split(r"\s+", m.group(1).replace("$\n", " ")):
                add(token.replace("$ ", " "), "CMake read it at configure time")
        link_text = "\n".join(re.findall(r"^\s*LINK_(?:LIBRARIES|PATH)\s*=\s*(.*)$", text, re.M))
    else:
        link_text = ""
        for dep in glob.glob(os.path.join(build_dir, "**", "*depend.make"), recursive=True):
            for line in open(dep, encoding="utf-8", errors="replace"):
                for token in line.replace(":", " ").split():
                    add(token, "a compiled source includes it (depend.make)")
        for link in glob.glob(os.path.join(build_dir, "**", "link.txt"), recursive=True):
            link_text += open(link, encoding="utf-8").read() + "\n"
    for token in link_text.split():
        for piece in token.split(","):  # -Wl,a,b
            if piece.startswith("/"):
                add(piece, "on a link line")
            elif piece.startswith("-l") and len(piece) > 2:
                for suffix in (".so", ".a"):
                    found = run(["c++", f"-print-file-name=lib{piece[2:]}{suffix}"]).stdout.strip()
                    if found.startswith("/") and os.path.exists(found):
                        add(found, f"linked as {piece}")
                        break

    cache = os.path.join(build_dir, "CMakeCache.txt")
    for line in open(cache, encoding="utf-8", errors="replace"):
        m = re.match(r"^([A-Za-z0-9_.+-]+):(FILEPATH|PATH)=(/.*)$", line.strip())
        if not m:
            continue
        name, kind, value = m.groups()
        if kind == "FILEPATH":
            add(value, f"CMakeCache.txt {name}")
        elif name.endswith("_DIR") and os.path.isdir(value):
            for config in glob.glob(os.path.join(value, "*[Cc]onfig.cmake")):
                add(config, f"CMakeCache.txt {name}")

    for exe in ("magcal", "magcald"):
        path = os.path.join(build_dir, "bin", exe)
        if not os.path.exists(path):
            continue
        for line in run(["ldd", path]).stdout.splitlines():
            m = re.search(r"=>\s*(/\S+)", line) or re.match(r"\s*(/\S+)", line)
            if m:
                add(m.group(1), f"{exe} loads it (ldd)")
    return files


def program_names(source_dir):
    names = set(DECLARED_PROGRAMS)
    for pattern in SOURCE_GLOBS:
        for path in glob.glob(os.path.join(source_dir, pattern), recursive=True):
            if os.path.basename(path) == os.path.basename(__file__):
                continue
            text = open(path, encoding="utf-8", errors="replace").read()
            for regex in PROGRAM_PATTERNS:
                names.update(regex.findall(text))
    return sorted(names)


def pg_bindir():
    """Where PostgreSQL's server programs (initdb, pg_ctl) are: not on PATH, the tests take them
    from `pg_config --bindir` (tests/storage/postgres/pg_test_server.hpp, pg_tool("X"))."""
    pg_config = shutil.which("pg_config")
    result = run([pg_config, "--bindir"], check=False) if pg_config else None
    return result.stdout.strip() if result and result.returncode == 0 else None


def program_files(names):
    """(files to map, programs not found at all). An absolute path found in a test's source that
    does not exist is one of its fallbacks (/usr/bin/chromium-browser): only names resolved on
    PATH (or in pg_bindir()) and DECLARED_PROGRAMS must exist."""
    files, missing = {}, []
    bindir = pg_bindir()
    for name in names:
        path = name if name.startswith("/") else (
            shutil.which(name) or (bindir and shutil.which(name, path=bindir)))
        if path is None or not os.path.exists(path):
            if not name.startswith("/") or name in DECLARED_PROGRAMS:
                missing.append(name)
            continue
        files[path] = f"program {name}"
    return files, missing


def module_files(source_dir):
    """The file of each module a test script imports, as /usr/bin/python3 finds it."""
    names = set()
    for path in glob.glob(os.path.join(source_dir, "tests", "**", "*.py"), recursive=True):
        names.update(MODULE_PATTERN.findall(open(path, encoding="utf-8").read()))
    files, missing = {}, []
    for name in sorted(names):
        result = run(["/usr/bin/python3", "-c",
                      f"import {name}; print(getattr({name}, '__file__', None) or '')"], check=False)
        if result.returncode != 0:
            missing.append(f"python module {name}")
        elif result.stdout.strip():  # built-in modules have no file
            files[result.stdout.strip()] = f"python module {name}"
    return files, missing


def owners(paths):
    """path -> set of packages, by dpkg -S; tries the path, its real path and the merged-/usr twin."""
    def candidates(path):
        real = os.path.realpath(path)
        out = []
        for p in (path, real):
            out.append(p)
            for a, b in (("/usr/lib/", "/lib/"), ("/usr/bin/", "/bin/"), ("/usr/sbin/", "/sbin/")):
                if p.startswith(a):
                    out.append(b + p[len(a):])
                elif p.startswith(b):
                    out.append(a + p[len(b):])
        return list(dict.fromkeys(out))

    wanted = sorted({c for p in paths for c in candidates(p)})
    found = {}
    for i in range(0, len(wanted), 200):
        result = run(["dpkg", "-S", *wanted[i:i + 200]], check=False)
        for line in result.stdout.splitlines():
            if line.startswith("diversion ") or ": " not in line:
                continue
            pkgs, path = line.split(": ", 1)
            for pkg in pkgs.split(", "):
                found.setdefault(path.strip(), set()).add(pkg.split(":")[0])
    return {p: set().union(*(found.get(c, set()) for c in candidates(p))) for p in paths}


def dependency_closure(packages):
    """Named packages and everything they Depend/PreDepend on, recursively (installed ones)."""
    if not packages:
        return set()
    result = run(["apt-cache", "depends", "--recurse", "--installed", "--no-recommends",
                  "--no-suggests", "--no-conflicts", "--no-breaks", "--no-replaces",
                  "--no-enhances", *packages], check=False)
    # Lines: a package (top level), "  Depends: NAME[:arch]" / " |PreDepends: <virtual>", and
    # the providers of a virtual package indented below it.
    closure = set(packages)
    entry = re.compile(r"^(?:\s*\|?(?:Pre)?Depends:\s*|\s*)<?([A-Za-z0-9][A-Za-z0-9.+-]*)")
    for line in result.stdout.splitlines():
        m = entry.match(line)
        if m:
            closure.add(m.group(1))
    return closure


def required_packages():
    out = run(["dpkg-query", "-W", "-f=${Package}\t${Priority}\n"]).stdout
    return {p for p, prio in (l.split("\t") for l in out.splitlines() if "\t" in l)
            if prio == "required"}


def violations(file_owners, why, allowed):
    """package -> example (file, why) for owners not allowed; None key for unowned files."""
    bad = {}
    for path, pkgs in sorted(file_owners.items()):
        if not pkgs:
            bad.setdefault(None, []).append((path, why[path]))
        elif not pkgs & allowed:
            for pkg in sorted(pkgs):
                bad.setdefault(pkg, []).append((path, why[path]))
    return bad


def describe(bad):
    lines = []
    for pkg, examples in sorted(bad.items(), key=lambda kv: kv[0] or ""):
        path, reason = examples[0]
        more = f" (+{len(examples) - 1} more)" if len(examples) > 1 else ""
        if pkg is None:
            for path, reason in examples:
                lines.append(f"  {path}: no Debian package owns it ({reason}); a fresh machine "
                             "lacks it")
        else:
            lines.append(f"  {pkg}: not installed by deploy/setup-deps.sh, yet {path} "
                         f"({reason}){more} comes from it")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build-dir", required=True)
    parser.add_argument("--source-dir", required=True)
    parser.add_argument("--self-check", nargs="*", default=["prometheus-cpp-dev", "python3-yaml"],
                        help="named packages to drop, one at a time, expecting a failure")
    args = parser.parse_args()
    build_dir = os.path.realpath(args.build_dir)
    source_dir = os.path.realpath(args.source_dir)
    if not os.path.exists(os.path.join(build_dir, "CMakeCache.txt")):
        print(f"FAILED: {build_dir} is not a configured build tree", file=sys.stderr)
        return 1

    named = run(["bash", os.path.join(source_dir, "deploy", "setup-deps.sh"), "--list",
                 "--tests"]).stdout.split()
    why = build_files(build_dir, [build_dir, source_dir])
    n_build = len(why)
    programs = program_names(source_dir)
    prog_files, missing = program_files(programs)
    mod_files, missing_modules = module_files(source_dir)
    missing += missing_modules
    for path, reason in {**prog_files, **mod_files}.items():
        why.setdefault(path, reason)
    file_owners = owners(list(why))
    required = required_packages()

    allowed = dependency_closure(named) | required
    bad = violations(file_owners, why, allowed)
    used = set().union(*file_owners.values()) if file_owners else set()
    print(f"dependency check: {n_build} system files the build used, {len(prog_files)} programs "
          f"({', '.join(programs)}), {len(mod_files)} python modules, {len(used)} owning packages; setup-deps.sh names "
          f"{len(named)}, which bring {len(allowed - required)} with their dependencies; "
          f"{len(required)} are Priority required")
    status = 0
    if missing:
        print("FAILED: programs the tests or the demo run are not installed: " +
              ", ".join(missing) + " (add their packages to deploy/setup-deps.sh)")
        status = 1
    if bad:
        print("FAILED: used but not installed by deploy/setup-deps.sh:\n" + describe(bad))
        status = 1

    for drop in args.self_check:
        if drop not in named:
            print(f"FAILED: self-check package {drop} is not in setup-deps.sh's list")
            status = 1
            continue
        reduced = dependency_closure([p for p in named if p != drop]) | required
        caught = violations(file_owners, why, reduced)
        if drop in caught:
            path, reason = caught[drop][0]
            print(f"self-check: without {drop} in the list the check fails and names it "
                  f"({path}, {reason})")
        else:
            print(f"FAILED: self-check: dropping {drop} from the list is not detected")
            status = 1
    if status == 0:
        print("dependency check passed")
    return status


if __name__ == "__main__":
    sys.exit(main())
