"""Fail when the project's user-facing files speak of how the project was developed rather than of the project.

README, docs, params and stage comments, docstrings and comments are read by users; the development history (which
session or round measured what, on which development machine, at which commit, on which date, in which named run)
lives in git. This script looks for the words that history is written in:

- development rounds and sessions ("session 18", "development round", "this session");
- commit-hash-like tokens in prose (7 to 40 hexadecimal characters with at least one digit and one letter);
- named development machines ("the Intel machine", "AVX-512 machine", "the AMD one");
- recipe names of the form "run A" to "run E";
- dates ("2026-11-25", "November 2026", "25 Nov 2026") and "yesterday", "this morning";
- the removed measurement diary (`measurements.md`).

Markdown and YAML files are read line by line; in Python files only comments and string literals (docstrings
included) are read, so code such as hexadecimal constants never matches.

    python tools/check_history_words.py [PATH ...]
        (default: README.md docs params.yaml dvc.yaml src pipeline benchmarks)

Prints one line per hit, `<file>:<line>: <kind>: "<text>"`, and exits with 1 if there is any.
"""

import io
import re
import sys
import tokenize
from collections.abc import Iterator
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_PATHS = ("README.md", "docs", "params.yaml", "dvc.yaml", "src", "pipeline", "benchmarks")
SUFFIXES = (".md", ".yaml", ".yml", ".py", ".txt", ".toml")
SKIPPED = ("__pycache__", "carp.egg-info")  # build outputs, not sources

_MONTHS = (
    "January|February|March|April|May|June|July|August|September|October|November|December"
    "|Jan|Feb|Mar|Apr|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec"
)
_HARDWARE = r"Intel|AMD|EPYC|Xeon|AVX-?512(?:[- ]BF16)?|AVX2|AMX|KVM"

RULES: tuple[tuple[str, re.Pattern[str]], ...] = (
    (
        "development round or session",
        re.compile(
            r"\b(?:development|dev)\s+(?:rounds?|sessions?)\b"
            r"|\bsessions?\s+\d+"
            r"|\brounds?\s+\d+\s*(?:-|to|and)\s*\d+\b|\bround\s+\d+\b"
            r"|\b(?:this|that|the\s+same|the\s+next|the\s+previous|an?\s+earlier|a\s+later|a\s+previous)\s+session\b",
            re.IGNORECASE,
        ),
    ),
    (
        "commit hash",
        re.compile(r"(?<![\w/.#:-])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w-])"),
    ),
    (
        "named development machine",
        re.compile(
            rf"\b(?:{_HARDWARE})(?:\s*\+\s*\w+)?(?:\s+(?:CPU|host|VM))?\s+(?:machine|host|box|one)s?\b"
            r"|\b(?:this|that|our|the\s+(?:other|first|second|third|slow(?:er)?|fast(?:er)?|earlier|current)"
            r")\s+(?:machine|host)s?\b",
            re.IGNORECASE,
        ),
    ),
    (
        # A capital letter after "run" is a recipe's name where punctuation or a word that follows names does; "runs
        # B tiny products" (B the batch size) is not.
        "named run",
        re.compile(
            r"\b[Rr]uns?\s+[A-E](?:\s*(?:,|and|or|to|-)\s*[A-E])*"
            r"(?=$|[),.:;'\u2019\"]|\s+(?:and|or|to|above|below|with|gave|of|in|at|on|here|there|used|was|is|had|has)\b)"
        ),
    ),
    (
        "date",
        re.compile(
            rf"\b(?:19|20)\d\d-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12]\d|3[01])\b"
            rf"|\b(?:{_MONTHS})\.?\s+(?:\d{{1,2}},?\s+)?(?:19|20)\d\d\b"
            rf"|\b\d{{1,2}}\s+(?:{_MONTHS})\.?\s+(?:19|20)\d\d\b"
            r"|\b(?:yesterday|this\s+morning|this\s+afternoon|last\s+night)\b",
            re.IGNORECASE,
        ),
    ),
    ("measurement diary", re.compile(r"measurements\.md")),
)


def find_in_text(text: str) -> Iterator[tuple[str, str]]:
    """Yield (kind, matched text) for every history word in `text`."""
    for kind, pattern in RULES:
        for match in pattern.finditer(text):
            yield kind, match.group(0)


def prose_lines(path: Path) -> Iterator[tuple[int, str]]:
    """Yield (line number, text) of the prose in `path`: every line, or a Python file's comments and strings."""
    text = path.read_text(encoding="utf-8")
    if path.suffix != ".py":
        yield from enumerate(text.splitlines(), start=1)
        return
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type in (tokenize.COMMENT, tokenize.STRING) or token.type == getattr(tokenize, "FSTRING_MIDDLE", -1):
            for offset, line in enumerate(token.string.splitlines()):
                yield token.start[0] + offset, line


def check_file(path: Path) -> list[str]:
    """Every hit in `path`, as `<path>:<line>: <kind>: "<text>"` lines."""
    return [
        f'{path}:{number}: {kind}: "{matched}"'
        for number, line in prose_lines(path)
        for kind, matched in find_in_text(line)
    ]


def files_under(paths: list[Path]) -> Iterator[Path]:
    """The checked files: each file named, and every file with a checked suffix under each folder named."""
    for path in paths:
        if path.is_dir():
            yield from sorted(
                p
                for p in path.rglob("*")
                if p.suffix in SUFFIXES and p.is_file() and not any(part in SKIPPED for part in p.parts)
            )
        elif path.exists():
            yield path


def main(arguments: list[str]) -> int:
    """Check the named paths (or the defaults, relative to the repository root); 1 if anything was found."""
    paths = [Path(argument) for argument in arguments] or [REPO_ROOT / name for name in DEFAULT_PATHS]
    hits = [hit for path in files_under(paths) for hit in check_file(path)]
    for hit in hits:
        print(hit)
    if hits:
        print(
            f"error: {len(hits)} development-history word(s): say what the project does and why, not how it was "
            "developed (the history stays in git)",
            file=sys.stderr,
        )
    return 1 if hits else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
