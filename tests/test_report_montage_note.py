"""The render montage labels site H's nearly uniform tiles with a note (not a failed render)."""

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402


def test_montage_labels_note_site_h_only():
    from dvsland.cli.cmd_render import montage_labels

    labels = montage_labels(["A", "H", "H~1"])
    assert labels[0] == "A"
    assert labels[1].split("\n")[0] == "H" and "H: flat, dusty" in labels[1] and "few features" in labels[1]
    assert labels[2].split("\n")[0] == "H~1"


def test_image_grid_writes_the_note_on_every_tile_of_its_column():
    from dvsland.report import style
    from dvsland.cli.cmd_render import montage_labels

    sites = ["A", "H"]
    cols = [f"site {s}" for s in montage_labels(sites)]
    fig = style.image_grid(np.random.default_rng(0).random((2, 2, 8, 8)), ["1000 m", "50 m"], cols)
    axes = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in axes[:2]] == ["site A", "site H"]
    notes = {(i, j): [t.get_text() for t in axes[2 * i + j].texts] for i in range(2) for j in range(2)}
    for i in range(2):
        assert notes[(i, 0)] == []
        assert len(notes[(i, 1)]) == 1 and notes[(i, 1)][0].startswith("H: flat, dusty")
    style.pyplot().close(fig)
