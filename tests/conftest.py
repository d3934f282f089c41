import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Blender reads BLENDER_USER_EXTENSIONS once, at the first `import bpy` (anywhere in the
# session): point it at a throw-away folder before any test module can import bpy, so tests
# never touch the user's extensions. Plain environment variable: no bpy needed here.
if "BLENDER_USER_EXTENSIONS" not in os.environ:
    _ext_dir = tempfile.mkdtemp(prefix="nlm-test-extensions-")
    os.environ["BLENDER_USER_EXTENSIONS"] = _ext_dir
    atexit.register(shutil.rmtree, _ext_dir, ignore_errors=True)
