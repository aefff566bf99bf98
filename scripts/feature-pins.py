#!/usr/bin/env python3
"""Keeps workspace-hack/Cargo.toml's feature pins current (issue 29).

`cargo run -- demo` builds the root package without its SQL engine, and maturin builds the Python
package's native module (`python/`) alone; the test command builds the whole workspace with every
target. Cargo gives a shared dependency the features its dependents
ask for in *that* build, so without pins the two builds compile arrow, parquet, syn, ... twice.
This script compares, with `cargo tree`, the features every package of the demo build gets with
those it gets in the test build, and pins the difference in workspace-hack/Cargo.toml (target
side as [dependencies], the proc-macro side, syn, as [build-dependencies]), repeating until the
two agree (a pin can bring in packages of its own).

  python3 scripts/feature-pins.py          # rewrite the pins
  python3 scripts/feature-pins.py --check  # exit 1 when they are stale (scripts/check.sh)
"""
import collections
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HACK = os.path.join(ROOT, "workspace-hack", "Cargo.toml")
PYHACK = os.path.join(ROOT, "python", "pins", "Cargo.toml")
# Workspace crates differ by design (the SQL feature); memchr differs only on the host side of the
# test build, which no crate of the demo build shares; syn is pinned on the host side.
SKIP = {"rtvtk", "rtvtk-viz", "rtvtk-python", "rtvtk-workspace-hack", "rtvtk-python-pins", "memchr"}
HOST = {"syn"}


def tree(args):
    out = subprocess.run(
        ["cargo", "tree", "--offline", "-f", "{p} {f}", "--prefix", "none", *args],
        cwd=ROOT, check=True, capture_output=True, text=True,
    ).stdout
    d = collections.defaultdict(list)
    for line in out.splitlines():
        parts = line.replace(" (*)", "").split()
        if len(parts) < 2:
            continue
        name, ver, rest = parts[0], parts[1].lstrip("v"), parts[2:]
        if rest and rest[0].startswith("("):
            rest = rest[1:]
        feats = frozenset(f for f in (rest[0].split(",") if rest else []) if f)
        if feats not in d[(name, ver)]:
            d[(name, ver)].append(feats)
    return d


def read_pins():
    pins = {}
    if not os.path.exists(HACK):
        return pins
    section = None
    for line in open(HACK):
        if line.startswith("["):
            section = line.strip()
            continue
        m = re.match(r'^(\S+) = \{ (?:package = "([^"]+)", )?version = "=([^"]+)", default-features = (\w+), features = \[(.*)\] \}', line)
        if m and section in ("[dependencies]", "[build-dependencies]"):
            name = m.group(2) or m.group(1)
            feats = set(re.findall(r'"([^"]+)"', m.group(5)))
            if m.group(4) == "true":
                feats.add("default")
            pins[(section, name, m.group(3))] = frozenset(feats)
    return pins


def header():
    text = open(HACK).read() if os.path.exists(HACK) else ""
    cut = text.find("\n[dependencies]")
    return text[:cut].rstrip("\n") + "\n" if cut >= 0 else text


def write(pins):
    lines = [header()]
    for section in ("[dependencies]", "[build-dependencies]"):
        lines.append("\n" + section)
        versions = {}
        for sec, name, ver in pins:
            if sec == section:
                versions.setdefault(name, set()).add(ver)
        for (sec, name, ver), feats in sorted(pins.items()):
            if sec != section:
                continue
            if sec == "[build-dependencies]":
                alias = name + ver.split(".")[0]
            elif len(versions[name]) > 1:
                # Two versions of one crate in the graph (getrandom 0.3 and 0.4): one key each.
                alias = name + "_" + ver.replace(".", "_")
            else:
                alias = name
            pkg = f'package = "{name}", ' if alias != name else ""
            fl = ", ".join(f'"{f}"' for f in sorted(feats - {"default"}))
            lines.append(
                f'{alias} = {{ {pkg}version = "={ver}", default-features = {str("default" in feats).lower()}, features = [{fl}] }}'
            )
    open(HACK, "w").write("\n".join(lines) + "\n")


def diff(part):
    """The packages whose features differ between the build `part` (cargo tree arguments) and
    the whole workspace's test build: the features the test build gives them."""
    full = tree(["--workspace", "-e", "normal,build,dev"])
    out = {}
    for (name, ver), variants in tree([*part, "-e", "normal,build"]).items():
        if name in SKIP or (name, ver) not in full:
            continue
        if sorted(map(sorted, variants)) != sorted(map(sorted, full[(name, ver)])):
            section = "[build-dependencies]" if name in HOST else "[dependencies]"
            out[(section, name, ver)] = max(full[(name, ver)], key=len)
    return out


def settle(path, part, check):
    """Pins in `path` until the build `part` gives every shared package the test build's features."""
    global HACK
    HACK = path
    pins = read_pins()
    for _ in range(10):
        d = {k: v for k, v in diff(part).items() if pins.get(k) != v}
        if not d:
            print(f"feature pins current: {len(pins)} crates pinned in {os.path.relpath(path, ROOT)}")
            return 0
        if check:
            for (sec, name, ver), feats in sorted(d.items()):
                print(f"stale pin: {name} {ver} needs {','.join(sorted(feats))} {sec}", file=sys.stderr)
            print("run: python3 scripts/feature-pins.py", file=sys.stderr)
            return 1
        pins.update(d)
        write(pins)
    print("the pins did not settle in 10 rounds", file=sys.stderr)
    return 1


def main():
    check = "--check" in sys.argv
    # The demo's build: pins every crate of the workspace shares (workspace-hack, under the root).
    # The Python package's native module, which maturin builds alone: its own pins crate
    # (python/pins), so the SQL engine it pins never enters the demo's build.
    return settle(os.path.join(ROOT, "workspace-hack", "Cargo.toml"), ["-p", "rtvtk", "--no-default-features"], check) or settle(
        PYHACK, ["-p", "rtvtk-python"], check
    )


if __name__ == "__main__":
    sys.exit(main())
