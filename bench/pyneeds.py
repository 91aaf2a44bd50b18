"""The Python packages a bench script needs, checked before it starts: a missing one is said with the
command that installs it, and the script exits 2, instead of a traceback from its first import.

    from pyneeds import need
    need(["numpy", "trimesh", "rtree", "scipy"], __file__)

(`./run setup test` makes target/pyenv with what the tests need; the bench scripts need more.)
"""
import importlib.util
import os
import sys

# The pip package of each import name, where they differ.
PIP_NAMES = {"sklearn": "scikit-learn", "skimage": "scikit-image", "nrrd": "pynrrd", "SimpleITK": "SimpleITK"}


def need(modules, script):
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if not missing:
        return
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    venv = os.path.join(root, "target", "pyenv", "bin", "python3")
    python = venv if os.path.exists(venv) else sys.executable
    packages = " ".join(PIP_NAMES.get(m, m) for m in missing)
    print(f"{os.path.basename(script)} needs the Python package(s) {', '.join(missing)}, which "
          f"{sys.executable} lacks: install them with `{python} -m pip install {packages}` and run it "
          f"with that Python", file=sys.stderr)
    sys.exit(2)
