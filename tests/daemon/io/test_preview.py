"""The PNG preview ``wristscan demo`` writes next to its PLY: a valid PNG of the asked size, with
something drawn, coloured by height; a missing ``plot`` extra is an error naming the extra."""

from __future__ import annotations

import builtins
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import png_size

from wristscan.daemon.io.preview import PreviewUnavailable, write_preview


def stepped_part() -> np.ndarray:
    """A 100 x 60 mm plate with a 20 mm high step on one half: two heights to colour."""
    x, y = np.meshgrid(np.linspace(-0.05, 0.05, 200), np.linspace(-0.03, 0.03, 120))
    z = np.where(x > 0.0, 0.02, 0.0)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def test_preview_is_a_png_of_the_asked_size_with_a_picture(tmp_path: Path) -> None:
    import matplotlib.image as mpimg

    out = write_preview(tmp_path / "scan.png", stepped_part(), title="test", size_px=(900, 400))
    data = out.read_bytes()
    assert png_size(data) == (900, 400)
    img = mpimg.imread(out)[:, :, :3]
    assert img.shape == (400, 900, 3)
    assert float(img.std()) > 0.05  # not blank
    # Coloured by height: the low and the high half of the step get clearly different colours.
    flat = img.reshape(-1, 3)
    coloured = flat[np.ptp(flat, axis=1) > 0.2]  # not grey: points and the colour bar
    assert coloured.shape[0] > 5000
    assert float(np.ptp(coloured, axis=0).max()) > 0.5
    assert not list(tmp_path.glob("*.tmp*")), "the atomic writer left a temporary file"


def test_empty_cloud_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no points"):
        write_preview(tmp_path / "x.png", np.full((3, 3), np.nan))
    assert not (tmp_path / "x.png").exists()


def test_missing_plot_extra_names_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_import = builtins.__import__

    def no_matplotlib(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    with pytest.raises(PreviewUnavailable, match=r"wristscan\[plot\]"):
        write_preview(tmp_path / "x.png", stepped_part())
    assert not (tmp_path / "x.png").exists()
