"""Tables as files: Markdown (pandas ``to_markdown``), LaTeX (pandas ``Styler.to_latex``, which
escapes ``& % $ # _ { } ~ ^ \\``) and CSV. An empty cell (NaN) stays empty, never zero."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd


def format_cell(v) -> str:
    """A cell as text: floats with 3 decimals, NaN and None empty."""
    if isinstance(v, float):
        return "" if np.isnan(v) else f"{v:.3f}"
    return "" if v is None else str(v)


def as_text(df: pd.DataFrame) -> pd.DataFrame:
    """The table with its index as columns and every cell as text."""
    return df.reset_index().map(format_cell) if df.index.names != [None] else df.map(format_cell)


def markdown(text: pd.DataFrame) -> str:
    """A GitHub Markdown table of a text frame (numbers kept as written)."""
    return text.to_markdown(index=False, disable_numparse=True)


LATEX_SPECIALS = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def latex(text: pd.DataFrame, caption: str) -> str:
    """A booktabs ``table`` of a text frame; cells and headers escaped by pandas, the caption alike."""
    styler = text.style.hide(axis="index").format(escape="latex").format_index(escape="latex", axis=1)
    title = "".join(LATEX_SPECIALS.get(c, c) for c in caption)
    return styler.to_latex(hrules=True, caption=title, position="ht")


def write(df: pd.DataFrame, stem: Path, caption: str) -> list[Path]:
    """``stem``.md, .tex and .csv of a table."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    text = as_text(df)
    md, tex, csv = stem.with_suffix(".md"), stem.with_suffix(".tex"), stem.with_suffix(".csv")
    md.write_text(f"**{caption}**\n\n{markdown(text)}\n")
    tex.write_text(latex(text, caption))
    (df.reset_index() if df.index.names != [None] else df).to_csv(csv, index=False, na_rep="")
    return [md, tex, csv]
