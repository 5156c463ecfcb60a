"""Check a normal (non-editable) install: build the wheel, install it into a fresh venv and
run tests against it from outside the repository.

    python scripts/check_wheel.py [--worktree] [--keep] [TEST_FILE ...]

The source is the committed tree (``git archive HEAD``; ``--worktree``: the working tree as
it is), so the wheel holds exactly what a release would. The tests are copied to a temporary
folder and run with ``--import-mode=importlib``, so ``navapp`` can only come from the
installed wheel (the script checks that it does, and that the packaged scenes are there).
Takes a few minutes (the venv installs every dependency); not part of the CI suite.
Default tests: test_study.py, test_simulation.py, test_api.py, test_examples.py.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_TESTS = ["test_study.py", "test_simulation.py", "test_api.py", "test_examples.py"]
PROBE = """
import navapp, sys
from navapp.simulation.scene import demo_scene, scene_dir, study_scenes
assert "site-packages" in navapp.__file__, navapp.__file__
assert len(study_scenes()) == 9 and (scene_dir() / "demo.toml").is_file()
demo_scene()
print("navapp", navapp.__version__, "from", navapp.__file__, "with", len(study_scenes()), "study scenes")
"""


def run(cmd, **kw):
    print("$", " ".join(map(str, cmd)), flush=True)
    subprocess.run(cmd, check=True, **kw)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tests", nargs="*", default=DEFAULT_TESTS, help="test files (names in tests/)")
    ap.add_argument("--worktree", action="store_true", help="build from the working tree, not HEAD")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="navapp-wheel-"))
    t0 = time.perf_counter()
    try:
        src = tmp / "src"
        if args.worktree:
            shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", "build", "*.egg-info", "__pycache__",
                                                                   ".*_cache", "navapp-demo"))
        else:
            src.mkdir()
            archive = subprocess.run(["git", "archive", "--format=tar", "HEAD"], cwd=ROOT, capture_output=True,
                                     check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", str(src), "-w", str(tmp / "whl")])
        wheel = next((tmp / "whl").glob("navapp-*.whl"))
        run([sys.executable, "-m", "venv", str(tmp / "venv")])
        py = tmp / "venv" / "bin" / "python"
        run([py, "-m", "pip", "install", "-q", f"{wheel}[test]"])
        work = tmp / "run"
        work.mkdir()
        # the tests and examples of the same source as the wheel (HEAD's with HEAD's wheel)
        shutil.copytree(src / "tests", work / "tests")
        shutil.copytree(src / "examples", work / "examples")
        run([py, "-c", PROBE], cwd=work)
        run([py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--import-mode=importlib", "--rootdir", str(work),
             *[f"tests/{t}" for t in args.tests]], cwd=work)
        print(f"wheel install OK ({wheel.name}, {time.perf_counter() - t0:.0f} s)")
        return 0
    except subprocess.CalledProcessError as exc:
        print(f"check_wheel: failed: {' '.join(map(str, exc.cmd))} (exit {exc.returncode})", file=sys.stderr)
        return 1
    finally:
        if args.keep:
            print("kept", tmp)
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
