"""The paper's plotted numbers, read from the pgfplots data inlined in its LaTeX source.

``python -m uwb_env.training.paper_data path/to/autocalibration-paper.tex`` extracts them into
``training/paper_reference.json`` (committed), which the reproduction script reads: Fig. 4's
error series (legend -> values per simulation step) and Fig. 5's box plots (quartiles,
whiskers, fliers) of anchor / tag translation error and x-axis rotation error.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

REFERENCE_PATH = Path(__file__).with_name("paper_reference.json")

_NUMBER = r"-?\d+(?:\.\d+)?(?:e-?\d+)?"
_TABLE = re.compile(r"\\addplot\s*\[([^\]]*)\]\s*table\s*\{%?\s*(.*?)\};", re.S)
_LEGEND = re.compile(r"\s*\\addlegendentry\{([^}]*)\}")
_PATH = re.compile(r"\\path\s*\[[^\]]*\]\s*((?:\s*-*\s*\(axis cs:[^)]*\))+)\s*--\s*cycle;", re.S)
_POINT = re.compile(rf"\(axis cs:({_NUMBER}),({_NUMBER})\)")


def _rows(body: str) -> list[tuple[float, float]]:
    values = [float(v) for v in re.findall(_NUMBER, body)]
    return list(zip(values[::2], values[1::2], strict=True))


def parse_series(tex: str) -> dict[str, list[float]]:
    """Every ``\\addplot ... table`` directly followed by a legend entry: legend -> y values."""
    series = {}
    for match in _TABLE.finditer(tex):
        legend = _LEGEND.match(tex, match.end())
        if legend:
            series[legend.group(1)] = [y for _, y in _rows(match.group(2))]
    return series


def parse_boxplots(tex: str) -> list[dict[str, float]]:
    """Box plots drawn as matplotlib exports them: a filled box path (q1..q3), a thick median
    line, vertical whisker lines from the box to the caps, and ``mark=+`` fliers."""
    boxes = []
    for match in _PATH.finditer(tex):
        pts = [(float(x), float(y)) for x, y in _POINT.findall(match.group(1))]
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        boxes.append({"x": (min(xs) + max(xs)) / 2, "half_width": (max(xs) - min(xs)) / 2,
                      "q1": min(ys), "q3": max(ys)})
    for opts, body in _TABLE.findall(tex):
        rows = _rows(body)
        for box in boxes:
            near = [y for x, y in rows if abs(x - box["x"]) < 1e-9]
            if "thick" in opts.split(",")[0] and len(rows) == 2 and rows[0][1] == rows[1][1]:
                if abs((rows[0][0] + rows[1][0]) / 2 - box["x"]) < 1e-9:
                    box["median"] = rows[0][1]
            elif "mark=+" in opts and len(near) == len(rows):
                box["fliers"] = near
            elif opts.strip().startswith("black") and len(near) == 2:  # a whisker: box edge -> cap
                end = near[1] if near[0] in (box["q1"], box["q3"]) else near[0]
                key = "whisker_low" if end <= box["q1"] else "whisker_high"
                box[key] = end
    return boxes


def _figure(tex: str, label: str) -> str:
    """The source of the figure environment holding ``\\label{label}``."""
    at = tex.index(f"\\label{{{label}}}")
    start = tex.rindex("\\begin{figure}", 0, at)
    return tex[start:tex.index("\\end{figure}", at)]


def extract(tex: str) -> dict:
    fig4 = parse_series(_figure(tex, "fig:simulation"))
    fig5 = _figure(tex, "fig:boxplots")
    split = fig5.index("\\label{subfig:boxplot_pos_error}")
    translation = parse_boxplots(fig5[:split])
    rotation = parse_boxplots(fig5[split:])
    by_x = {round(b["x"]): b for b in translation}
    return {
        "source": "autocalibration-paper.tex (pgfplots data of Fig. 4 and Fig. 5)",
        "fig4_anchor_error_m": {k: v for k, v in fig4.items() if k.startswith("A")},
        "fig4_tag_error_m": {k: v for k, v in fig4.items() if k.startswith("Tag")},
        "fig5_anchor_translation_error_m": by_x[1],
        "fig5_tag_translation_error_m": by_x[2],
        "fig5_x_axis_rotation_error_rad": rotation[0],
    }


def load_reference() -> dict:
    return json.loads(REFERENCE_PATH.read_text())


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m uwb_env.training.paper_data path/to/autocalibration-paper.tex")
    data = extract(Path(sys.argv[1]).read_text())
    REFERENCE_PATH.write_text(json.dumps(data, indent=1) + "\n")
    print(f"wrote {REFERENCE_PATH}")
