"""The output layer's figures: the writer loaded ahead, and a figure written whole."""

from __future__ import annotations

import sys
from pathlib import Path

from scanguard.fsutil import load_figure_writer, save_figure


def test_the_figure_writer_loads_ahead_and_writes_a_png(tmp_path: Path) -> None:
    load_figure_writer()
    import matplotlib

    assert "matplotlib.pyplot" in sys.modules and "matplotlib.image" in sys.modules
    assert matplotlib.get_backend().lower() == "agg"
    load_figure_writer()  # again: nothing to do
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0.0, 1.0], [1.0, 0.0])
    out = save_figure(fig, tmp_path / "f.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]  # no temporary left
    assert not plt.get_fignums()  # closed
