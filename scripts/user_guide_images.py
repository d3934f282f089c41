"""Walk docs/user_guide.md in a Blender-only interpreter and write the pictures it shows.

    python scripts/user_guide_images.py            # writes docs/user_guide_*.png

Builds the linux-x64 extension zip (``scripts/build_extension.py``), then runs
``scripts/user_guide_walk.py`` through ``scripts/blender_only.py``: the zip installed into a fresh
user-extensions folder, the guide's steps pressed with their default settings, the previews and the
render written by the add-on itself. Prints every step; exits 1 when a step did not finish.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import blender_only  # noqa: E402
import build_extension  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="user_guide_") as tmp:
        tmp = Path(tmp)
        (zip_path,) = build_extension.build(
            ["linux-x64"], tmp / "dist", ROOT / "cache" / "wheels", tmp / "build", log=lambda *_: None
        )
        work = tmp / "work"
        work.mkdir()
        proc = blender_only.run(
            ROOT / "scripts" / "user_guide_walk.py", [str(zip_path), str(ROOT / "docs"), str(work)], tmp, cwd=work
        )
    print("\n".join(line for line in proc.stdout.splitlines() if line.startswith("[")))
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        print(proc.stdout[-3000:] + proc.stderr[-3000:], file=sys.stderr)
        return 1
    steps = json.loads(lines[-1][len("RESULT ") :])
    failed = [s for s in steps if s["result"] != ["FINISHED"] and s["step"] != "texture"]
    for s in failed:
        print(f"step did not finish: [{s['section']}] {s['step']}: {s['result']}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
