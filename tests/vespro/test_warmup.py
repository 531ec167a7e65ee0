"""Set-up's warm-up (``python3 -m vespro.warmup``) reaches every compiled kernel."""

import pytest


def test_kernel_modules_are_found():
    from vespro.warmup import kernel_modules

    mods = kernel_modules()
    for m in ("vespro.bsp", "vespro.extraction", "vespro.projection", "vespro.selection", "vespro.visibility",
              "vespro.init.search", "vespro.edgefit", "vespro.numerics"):
        assert m in mods
    assert "vespro.jit" not in mods and "vespro.warmup" not in mods


@pytest.mark.slow
def test_warm_up_compiles_every_kernel_called_from_python(capsys):
    """A kernel added later and not reached by the warm-up would compile in a user's
    first run instead (tens of seconds before the first frame): named here."""
    from vespro.warmup import main

    assert main([]) == 0
    out, err = capsys.readouterr()
    assert "not compiled" not in err, err
    assert "kernels ready" in out and "2/3 frames tracking" in out


def test_cached_kernels_older_than_the_shared_helpers_are_forgotten(tmp_path):
    """A kernel compiles ``vespro.numerics``' helpers into itself, and numba checks a cached
    kernel against its own file only: caches older than the helpers' file are dropped (they
    compile again once), newer ones kept."""
    import os

    from vespro.jit import drop_stale_caches

    (tmp_path / "init" / "__pycache__").mkdir(parents=True)
    (tmp_path / "__pycache__").mkdir()
    old = [tmp_path / "__pycache__" / "edgefit.k-1.py311.nbi", tmp_path / "init" / "__pycache__" / "search.r-2.py311.nbi"]
    new = tmp_path / "__pycache__" / "bsp.b-3.py311.nbi"
    data = tmp_path / "__pycache__" / "edgefit.k-1.py311.1.nbc"  # machine code: left for numba to overwrite
    shared = tmp_path / "numerics.py"
    for p in (*old, new, data, shared):
        p.write_text("x")
    for p in (*old, data):
        os.utime(p, (1000.0, 1000.0))
    os.utime(shared, (2000.0, 2000.0))
    os.utime(new, (3000.0, 3000.0))
    assert drop_stale_caches(tmp_path, shared) == 2
    assert not any(p.exists() for p in old) and new.exists() and data.exists()
    assert drop_stale_caches(tmp_path, tmp_path / "absent.py") == 0
