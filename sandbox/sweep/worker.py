"""A sweep's run process: ``python -m sandbox.sweep.worker RUN_DIR`` runs ``RUN_DIR/spec.json``.

Its exit code is ``sandbox run``'s (0 success, 1 a criterion failed, 2 invalid,
3 unstable or error, 130 interrupted); its outputs are ``sandbox run``'s, in
``RUN_DIR``. An invalid level still leaves a ``summary.json`` that says so.
"""

from __future__ import annotations

import json
import pathlib
import sys

from sandbox.sweep.execute import die_with_parent


def main(argv: list[str]) -> int:
    die_with_parent()
    out = pathlib.Path(argv[0])
    spec = json.loads((out / "spec.json").read_text())
    from sandbox.io.outputs import write_json_atomic
    from sandbox.runner import RunOptions, run_level

    opts = RunOptions(out=out, frames=spec.get("frames"), frames_every=int(spec.get("frames_every") or 0),
                      progress=False, overrides=spec.get("overrides") or None)
    code, summary = run_level(spec["level"], opts)
    if summary.get("status") == "invalid":
        write_json_atomic(out / "summary.json", {"status": "invalid", "success": False,
                                                 "message": summary.get("errors", "")})
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
