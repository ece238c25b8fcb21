"""The package and its tests reference nothing outside the repository: a fresh clone is all they need.

A static scan of every Python source of the repository (packages, scripts, tests): no path literal that climbs out
of it (``../x``, a ``".."`` component, ``Path(__file__).parents[k]`` past the root), and no absolute path of a
particular machine (home or work directories). Fixtures live in ``tests/fixtures/``.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE_DIRS = ("envs", "rotation", "adapters", "scripts", "tests")

CLIMB = re.compile(r"""["']\.\./|/\.\./|["']\.\.["']\s*[/),]|/\s*["']\.\.["']""")
"""A parent-directory step in a path: a literal "../shared" or "a/../b", or ".." joined as a component."""
MACHINE_PATH = re.compile(r"""["'](/root/|/home/|/Users/|/mnt/|[A-Za-z]:\\\\Users)""")
"""A string literal that starts with a directory of one machine or user."""
PARENTS_INDEX = re.compile(r"__file__\)\.resolve\(\)\.parents\[(\d+)\]")
PARENT_CHAIN = re.compile(r"__file__\)\.resolve\(\)((?:\.parent)+)")


def sources() -> list[Path]:
    files = [p for d in SOURCE_DIRS if (ROOT / d).is_dir() for p in sorted((ROOT / d).rglob("*.py"))]
    this = Path(__file__).resolve()  # holds the patterns themselves, as examples
    return [p for p in files if p != this and not any(part.startswith(".") or part == "__pycache__" for part in
                                                      p.relative_to(ROOT).parts)]


def outside_references(rel: Path, text: str) -> list[str]:
    """``file:line: text`` of every reference in ``text`` (the source at ``rel``, relative to the root) that points
    outside the repository."""
    to_root = len(rel.parts)  # parent steps from the file up to the root
    found = []
    for n, line in enumerate(text.splitlines(), 1):
        code = line.split("#", 1)[0]
        levels = [int(m) + 1 for m in PARENTS_INDEX.findall(code)]  # parents[k] climbs k + 1 directories
        levels += [chain.count(".parent") for chain in PARENT_CHAIN.findall(code)]
        if CLIMB.search(code) or MACHINE_PATH.search(code) or any(k > to_root for k in levels):
            found.append(f"{rel}:{n}: {line.strip()}")
    return found


def test_the_scan_catches_what_it_should():
    """The patterns themselves, on the kind of line that once read a fixture from beside the repository."""
    bad = ['FIXTURE = Path(__file__).resolve().parents[2] / ".." / "shared" / "x.npz"',
           'data = np.load("../shared/fixtures/x.npz")', 'OUT = Path("/home/lab/runs")',
           'p = Path(__file__).resolve().parents[3] / "x"', 'p = Path(__file__).resolve().parent.parent.parent.parent']
    good = ['ROOT = Path(__file__).resolve().parents[2]', 'FIXTURE = ROOT / "tests" / "fixtures" / "x.npz"',
            'text = "a range 1..2"  # ../ in a comment is fine', "names = 'cylinder_0'..'8'"]
    rel = Path("tests", "deploy", "test_x.py")  # two directories deep, as a real test file
    for line in bad:
        assert outside_references(rel, line), line
    for line in good:
        assert not outside_references(rel, line), line


def test_no_source_references_a_path_outside_the_repository():
    files = sources()
    assert len(files) > 50, f"found only {len(files)} Python files under {SOURCE_DIRS}: wrong root {ROOT}?"
    found = [ref for f in files for ref in outside_references(f.relative_to(ROOT), f.read_text("utf-8"))]
    assert not found, "paths outside the repository (put fixtures in tests/fixtures/):\n" + "\n".join(found)


def test_the_filterbank_fixture_ships_with_its_provenance():
    fixtures = ROOT / "tests" / "fixtures"
    assert (fixtures / "kaldi_fbank_48k_128mel.npz").stat().st_size > 100_000
    readme = (fixtures / "README.md").read_text()
    assert "torchaudio" in readme and "2.9.1" in readme and "kaldi_fbank_48k_128mel.npz" in readme
