"""Draw docs/gyro-kit-wiring.png, the wiring of docs/gyro-kit.md (matplotlib, no pyplot).

Run from the repository root: ``python firmware/wiring_diagram.py [OUT.png]``. The table in
docs/gyro-kit.md is the reference; this figure draws the same connections.
"""

from __future__ import annotations

import sys

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import FancyBboxPatch

# (board pin, signal, through the 74HC4050 (3.3 V), sensor pin, colour)
WIRES = [
    ("SCK (PB1)", "SCK  8 MHz", True, "SCLK / SPC", "#1f77b4"),
    ("MOSI (PB2)", "MOSI", True, "SDI / SDA", "#2ca02c"),
    ("D10 (PB6)", "CS", True, "nCS", "#9467bd"),
    ("MISO (PB3)", "MISO (3.3 V in)", False, "SDO / AD0", "#ff7f0e"),
    ("D4 (PD4, ICP1)", "data ready", False, "INT (ICM: INT1)", "#d62728"),
    ("3V3", "3.3 V", False, "VDD + VDDIO", "#e377c2"),
    ("GND", "ground", False, "GND", "#444444"),
]


def draw(path: str) -> None:
    fig = Figure(figsize=(10.5, 5.2), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0, 105)
    ax.set_ylim(0, 52)
    ax.axis("off")

    def box(x: float, y: float, w: float, h: float, title: str, sub: str, color: str) -> None:
        ax.add_patch(
            FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.6", fc=color, ec="black", lw=1.2)
        )
        ax.text(x + w / 2, y + h + 2.2, title, ha="center", va="bottom", fontsize=11,
                weight="bold")  # fmt: skip
        ax.text(x + w / 2, y + h + 0.6, sub, ha="center", va="bottom", fontsize=8.5)

    box(3, 4, 24, 38, "Arduino Micro", "ATmega32u4, 5 V, 16 MHz, USB to host", "#e8f1fb")
    box(44, 25.8, 16, 14.4, "CD74HC4050", "hex buffer: VCC 3V3, GND, 100 nF", "#fdf3e1")
    box(76, 4, 24, 38, "gyro breakout", "MPU-6000 or ICM-42688-P, 3.3 V", "#eaf6ea")

    ys = [38 - 5 * i for i in range(len(WIRES))]
    for y, (pin, signal, buffered, spin, color) in zip(ys, WIRES, strict=True):
        ax.text(26, y, pin, ha="right", va="center", fontsize=9)
        ax.text(77, y, spin, ha="left", va="center", fontsize=9)
        if buffered:
            ax.plot([27.6, 43.4], [y, y], color=color, lw=2.2)
            ax.plot([60.6, 75.4], [y, y], color=color, lw=2.2)
            ax.text(44.6, y, "in", ha="left", va="center", fontsize=7.5)
            ax.text(59.4, y, "out", ha="right", va="center", fontsize=7.5)
            ax.text(35.5, y + 0.8, signal, ha="center", va="bottom", fontsize=8, color=color)
        else:
            ax.plot([27.6, 75.4], [y, y], color=color, lw=2.2)
            ax.text(51.5, y + 0.8, signal, ha="center", va="bottom", fontsize=8, color=color)
    ax.text(52.5, 1.0, "5 V outputs reach the 3.3 V sensor only through the buffer; the "
            "sensor's 3.3 V outputs drive the 5 V MCU directly (its input-high threshold "
            "is 1.9 V).", ha="center", va="bottom", fontsize=8, style="italic")  # fmt: skip
    fig.savefig(path)


if __name__ == "__main__":
    draw(sys.argv[1] if len(sys.argv) > 1 else "docs/gyro-kit-wiring.png")
