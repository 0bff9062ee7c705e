"""What the quick commands and a batch worker import: only what they use (the numerical libraries
come with the stage or method that needs them)."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from pipeline.core.lazy import LazyModule

#: libraries none of the quick commands needs (numpy, pydantic, typer and rich they do)
HEAVY = {"cv2", "scipy", "matplotlib", "filterpy", "numba", "trimesh", "pyrender", "rerun", "dask", "distributed",
         "ezc3d", "OpenGL"}

_LOADED = "import atexit, sys; atexit.register(lambda: print('LOADED', *sorted({m.split('.')[0] for m in sys.modules})))"


def loaded(code: str) -> set[str]:
    """The top-level modules a fresh interpreter holds after running ``code``."""
    res = subprocess.run([sys.executable, "-c", f"{_LOADED}\n{code}"], capture_output=True, text=True, timeout=120)
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("LOADED"))
    return set(line.split()[1:])


@pytest.mark.parametrize("args", [["--help"], ["methods"], ["methods", "ekf"], ["scenarios"]])
def test_quick_commands_import_no_numerical_library_beyond_numpy(args: list[str]) -> None:
    mods = loaded(f"import sys; sys.argv = ['stereotrack', *{args!r}]\nfrom pipeline.app.cli import main\nmain()")
    assert not mods & HEAVY, sorted(mods & HEAVY)


def test_listing_the_methods_imports_no_method() -> None:
    """`stereotrack methods` prints from the written-down catalogue: not even numpy or pydantic."""
    from pipeline.core.plugins import DETECTOR_GROUP, ESTIMATOR_GROUP, has_plugins

    if has_plugins(ESTIMATOR_GROUP, DETECTOR_GROUP):
        pytest.skip("a stereotrack plugin is installed here: the listing imports the registries (as it should)")
    mods = loaded("import sys; sys.argv = ['stereotrack', 'methods']\nfrom pipeline.app.cli import main\nmain()")
    assert not mods & {"numpy", "pydantic", "detectors"}, sorted(mods & {"numpy", "pydantic", "detectors"})


def test_the_catalogue_is_what_the_registries_say() -> None:
    """The written-down listing equals the registries' built-ins (after adding or renaming a method or
    detector, or changing its docstring: `python -m pipeline.app.catalogue`)."""
    from pipeline.app._catalogue import DETECTORS, ESTIMATORS
    from pipeline.app.catalogue import live

    est, det = live(builtin_only=True)
    assert (ESTIMATORS, DETECTORS) == (est, det), "stale: run `python -m pipeline.app.catalogue`"


def test_a_batch_worker_imports_no_scipy_filterpy_or_matplotlib() -> None:
    """The worker's own imports; each stage imports what it needs when it runs."""
    mods = loaded("import pipeline.app.run")
    assert not mods & {"scipy", "filterpy", "matplotlib", "numba", "rerun", "pyrender"}, sorted(mods)


def test_estimating_a_rendered_clip_imports_no_opencv(mp4_clip, tmp_path) -> None:
    """`stereotrack estimate` reads detections, not frames: OpenCV (tens of ms to import) stays out
    where the clip says its frame rate (clip.json; otherwise the video header is read for it)."""
    import shutil

    from detectors.stage import detect_clip
    from pipeline.core.settings import RunSettings

    clip = shutil.copytree(mp4_clip, tmp_path / "clip")
    detect_clip(clip, RunSettings(detector="blob"))
    args = ["stereotrack", "estimate", str(clip), "--methods", "ekf"]
    mods = loaded(f"import sys; sys.argv = {args!r}\n"
                  "from pipeline.app.cli import main\ntry:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e")
    assert "cv2" not in mods and "pipeline" in mods, sorted(mods)
    assert (clip / "out" / "estimates" / "ekf.csv").is_file()


def test_a_lazy_module_is_the_module_on_first_use_from_many_threads() -> None:
    """Eight threads touching it first at once all get the real attributes (no half-made module)."""
    lazy = LazyModule("colorsys")
    got: list[object] = []
    threads = [threading.Thread(target=lambda: got.append(lazy.rgb_to_hsv)) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    import colorsys

    assert got == [colorsys.rgb_to_hsv] * 8 and lazy.rgb_to_hsv is colorsys.rgb_to_hsv


def test_opencv_constants_written_as_numbers_are_opencvs() -> None:
    """The termination criteria spelled as numbers (so that importing the module needs no OpenCV)."""
    import cv2

    from detectors.meanshift import CRITERIA
    from pipeline.core.camera import UNDISTORT_CRITERIA

    both = cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS
    assert UNDISTORT_CRITERIA[0] == both and CRITERIA[0] == both


def test_the_default_estimate_stage_imports_no_filterpy_or_scipy_stats(tmp_path) -> None:
    """Every default method (point and target) builds the numpy filters of
    :mod:`pipeline.estimators.filters`: filterpy's classes would import scipy.stats (about a second).
    The χ² quantiles of a default run come without scipy.special (0.15–0.2 s). The methods run in
    this process (``--workers 1``), so that whatever they import is seen here."""
    import shutil
    from pathlib import Path

    clip = tmp_path / "clip"
    shutil.copytree(Path(__file__).parents[2] / "data" / "clips" / "four_point_small", clip)
    code = ("import sys, contextlib\nfrom pipeline.app.cli import main\n"
            f"for args in (['detect', {str(clip)!r}], ['estimate', {str(clip)!r}, '--workers', '1']):\n"
            "    sys.argv = ['stereotrack', *args]\n"
            "    with contextlib.suppress(SystemExit):\n        main()\n"
            "print('STATS', 'scipy.stats' in sys.modules, 'SPECIAL', 'scipy.special' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", f"{_LOADED}\n{code}"], capture_output=True, text=True, timeout=300)
    assert all((clip / "out" / "estimates" / f"{m}.csv").is_file() for m in ("ukf", "pnp_kf", "kf3d_rts")), res.stderr
    mods = set(next(ln for ln in res.stdout.splitlines() if ln.startswith("LOADED")).split()[1:])
    assert "filterpy" not in mods and "STATS False SPECIAL False" in res.stdout, res.stdout[-500:]
