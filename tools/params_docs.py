"""Write the params reference page docs/params.md from the config classes' docstrings, or check that it is current.

python tools/params_docs.py           # (re)write docs/params.md (`make docs`)
python tools/params_docs.py --check   # exit 1 if a param is undocumented or the page is out of date (`make lint`)
"""

import argparse
import sys
from pathlib import Path

from carp.config_docs import documentation_problems, params_reference

PAGE = Path(__file__).resolve().parents[1] / "docs" / "params.md"


def main() -> int:
    """Write or check the page; 1 with one `error:` line per problem."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="check instead of writing")
    arguments = parser.parse_args()
    problems = documentation_problems()
    for problem in problems:
        print(f"error: src/carp/config.py: {problem}", file=sys.stderr)
    if problems:
        return 1
    page = params_reference()
    if not arguments.check:
        temporary = PAGE.with_name(f".{PAGE.name}.tmp")
        temporary.write_text(page)
        temporary.replace(PAGE)
        return 0
    if not PAGE.exists() or PAGE.read_text() != page:
        print(f"error: {PAGE}: out of date with src/carp/config.py; run `make docs`", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
