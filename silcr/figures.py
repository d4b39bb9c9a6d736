"""What every figure of `silcr plot` shares: one colour per group, the panel grid, the steps axis."""

from __future__ import annotations

from silcr.common.run_records import label_key


def group_colours(labels: set[str]) -> dict[str, str]:
    """One colour per group, the same in every panel (even where a panel lacks some group) and in
    `--stats rliable`'s interval figure: matplotlib's cycle in the groups' sorted order."""
    import matplotlib.pyplot as plt

    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {label: palette[i % len(palette)] for i, label in enumerate(sorted(labels, key=label_key))}


def steps_tick(value: float, _position: int) -> str:
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def panels(count: int):
    """A figure with one panel per task, three to a row; the grid's unused panels hidden."""
    import matplotlib.pyplot as plt

    cols = min(3, count)
    rows = (count + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    for ax in list(axes.flat)[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)[:count]
