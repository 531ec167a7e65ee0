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
