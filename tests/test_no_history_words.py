"""The product speaks of what it is, not of how it was made: no development-history words in the tracked files.

The history of what was tried lives in git; a user cannot know what a numbered work item or work period of the
project means. The patterns are assembled from pieces so that this file does not match itself.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_WORK = "|".join(("st" + "op", "is" + "sue"))
#: a numbered work item or work period ("<word> 12", "<word>s 3 and 4", "<word> #7", "<word>12")
NUMBERED = re.compile(rf"\b(?:{_WORK})s?\s?#?\d+", re.IGNORECASE)
#: who steered the work and in what
PROCESS = re.compile("|".join((r"\bsess" + r"ions?\b", r"\bproject " + "brief", r"\bthe " + r"brief\b",
                               r"\bsteer" + r"ing (?:the|this) project", r"\bpeople steer" + "ing",
                               "DESIGN" + r"\.md")), re.IGNORECASE)
BINARY_SUFFIXES = {".png", ".jpg", ".safetensors", ".parquet", ".rrd", ".bag", ".mcap", ".pt", ".npz", ".npy"}


def tracked_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
        return [ROOT / p for p in out.decode().split("\0") if p]
    except (OSError, subprocess.CalledProcessError):  # not a git checkout: every file but the virtual environment
        return [p for p in ROOT.rglob("*") if p.is_file() and not {".venv", ".git", "runs"} & set(p.parts)]


def text_of(path: Path) -> str | None:
    if path.suffix in BINARY_SUFFIXES or not path.is_file():
        return None
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", errors="replace")


def offences(pattern: re.Pattern[str], text: str) -> list[str]:
    return [m.group(0) for m in pattern.finditer(text)]


def test_the_patterns_match_what_they_forbid() -> None:
    """Each pattern catches its kind (so the checks below can fail) and leaves ordinary prose alone."""
    word = "st" + "op"
    assert offences(NUMBERED, f"since {word} 35, see {word}s 3 and {word.upper()}42") == [
        f"{word} 35", f"{word}s 3", f"{word.upper()}42"]
    assert offences(NUMBERED, "is" + "sue #28 item 3") == ["is" + "sue #28"]
    assert offences(PROCESS, "one sess" + "ion was lent a GPU") == ["sess" + "ion"]
    assert not offences(NUMBERED, "sphere tracing halts 1e-6 short; the filter stops after 3 rejections")
    assert not offences(PROCESS, "steering vector of the array; brief(text) shortens a description")


def test_no_history_words_in_tracked_files() -> None:
    bad: list[str] = []
    for path in tracked_files():
        rel = path.relative_to(ROOT).as_posix()
        if NUMBERED.search(path.name):
            bad.append(f"{rel}: file name")
        text = text_of(path)
        if text is None:
            continue
        for pattern in (NUMBERED, PROCESS):
            for m in pattern.finditer(text):
                line = text.count("\n", 0, m.start()) + 1
                bad.append(f"{rel}:{line}: {m.group(0)!r}")
    assert not bad, f"{len(bad)} development-history words:\n" + "\n".join(bad[:50])
