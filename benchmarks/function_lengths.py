"""Functions in ``src/`` longer than a reader can hold in their head.

Counts each function's lines of code: its lines less blank lines, comment-only lines and
its docstring (nested functions count in their parent too, as a reader reads them
there). Prints every function over ``--limit`` (default 120), longest first, and exits 1
if there is any, so that it can guard a refactoring.

Run: ``.venv/bin/python benchmarks/function_lengths.py [--limit 120]``
"""

from __future__ import annotations

import argparse
import ast
import io
import tokenize
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "emccdcal"


def _code_lines(source: str) -> set[int]:
    """Line numbers that hold code (not blank, not only a comment)."""
    lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type not in (
            tokenize.COMMENT,
            tokenize.NL,
            tokenize.NEWLINE,
            tokenize.INDENT,
            tokenize.DEDENT,
            tokenize.ENCODING,
            tokenize.ENDMARKER,
        ):
            lines.update(range(tok.start[0], tok.end[0] + 1))
    return lines


def function_lengths(root: Path = SRC):
    """``(lines of code, "file:line name")`` of every function under ``root``."""
    out = []
    for path in sorted(root.rglob("*.py")):
        source = path.read_text()
        code = _code_lines(source)
        for node in ast.walk(ast.parse(source)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            span = set(range(node.lineno, node.end_lineno + 1)) & code
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):  # the docstring
                span -= set(range(body[0].lineno, body[0].end_lineno + 1))
            out.append((len(span), f"{path.relative_to(root.parent)}:{node.lineno} {node.name}"))
    return sorted(out, reverse=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=int, default=120)
    args = ap.parse_args(argv)
    long = [(n, where) for n, where in function_lengths() if n > args.limit]
    for n, where in long:
        print(f"{n:5d}  {where}")
    print(f"{len(long)} function(s) over {args.limit} lines of code")
    return 1 if long else 0


if __name__ == "__main__":
    raise SystemExit(main())
