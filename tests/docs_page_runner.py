"""Run one documentation page's examples as a reader would: this file is the program of a
fresh ``python`` process (``python -c``), started in a copy of the docs' world, that
imports nothing of emccdcal itself.

``argv``: the steps (a JSON file) and where to write what happened (a JSON file). A step
is ``{"where", "kind": "python", "code"}`` — a block executed in the page's one namespace,
as a reader pastes the page's blocks in order into one interpreter — or ``{"where",
"kind": "shell", "argv", "remove", "reset_db"}`` — the installed ``emccdcal`` command
run in its own process, after removing what the page makes itself (``remove``) and,
where the page starts its own database, the world's (``reset_db``). Only the standard
library is used here, so that nothing is imported before the page's first line.
"""

import json
import os
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path


def main(steps_file, results_file, command):
    steps = json.loads(Path(steps_file).read_text(encoding="utf-8"))
    namespace = {"__name__": "__main__"}
    results = []
    for step in steps:
        t0 = time.perf_counter()
        if step["kind"] == "python":
            try:
                exec(compile(step["code"], step["where"], "exec"), namespace)
                error = None
            except Exception as exc:  # noqa: BLE001 - reported with the page's line
                error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()[-1500:]}"
            results.append({"item": step["item"], "error": error})
            continue
        remove = step.get("remove")
        if remove:
            path = Path(remove)
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(
                missing_ok=True
            )
        if step.get("reset_db"):
            Path(os.environ["EMCCDCAL_DB"]).unlink(missing_ok=True)
        try:
            done = subprocess.run(
                [command, *map(os.path.expanduser, step["argv"])],  # as a shell, "~"
                capture_output=True,
                text=True,
                encoding="utf-8",
                errors="backslashreplace",
                timeout=900,
            )
            code, out, err = done.returncode, done.stdout, done.stderr
        except subprocess.TimeoutExpired as exc:
            code, out, err = None, "", f"timed out after {exc.timeout} s"
        results.append(
            {
                "item": step["item"],
                "code": code,
                "out": out,
                "err": err,
                "seconds": time.perf_counter() - t0,
            }
        )
    Path(results_file).write_text(json.dumps(results), encoding="utf-8")


if __name__ == "__main__":  # run as the page's program, never imported
    main(*sys.argv[1:4])
