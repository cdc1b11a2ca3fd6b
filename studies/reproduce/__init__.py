"""Reproductions of the seed papers' experiments: ``rollingstar reproduce <paper>``.

Each paper has a module ``studies/reproduce/<paper>.py`` with

    def run(quick: bool, plots_dir: Path | None, seed: int) -> list[Row]

and one data file ``studies/reproduce/data/<paper>.yaml`` holding the values the paper reports,
each with the table or figure it comes from. Paper values are only ever printed in the "paper"
column; "ours" is always measured by the run that prints it.
"""
from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

from rollingstar.errors import UserError

PAPERS = ("he2021a", "he2021b", "fu2022", "liu2013")
DATA_DIR = Path(__file__).parent / "data"


@dataclass(frozen=True)
class Row:
    """One reproduced quantity: the paper's value (or bound, as text), ours, and how we got ours."""

    quantity: str
    condition: str
    paper: float | str | None
    ours: float | None
    unit: str
    source: str = ""  # table/figure of the paper
    trials: int | None = None  # Monte Carlo count behind "ours"
    seed: int | None = None
    note: str = ""

    @property
    def ratio(self) -> float | None:
        if isinstance(self.paper, (int, float)) and self.ours is not None and self.paper != 0:
            return self.ours / self.paper
        return None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["ratio"] = self.ratio
        return d


def paper_values(paper: str) -> dict:
    """The paper's reported values, keyed by quantity id (see the YAML file for sources)."""
    with open(DATA_DIR / f"{paper}.yaml") as fh:
        return yaml.safe_load(fh)


def run_reproduction(paper: str, quick: bool = False, plots_dir: Path | None = None, seed: int = 1) -> list[Row]:
    if paper not in PAPERS:
        raise UserError(f"unknown paper {paper!r}; choose one of: {', '.join(PAPERS)}")
    # imported by name: each paper's module imports Row from this package
    module = importlib.import_module(f"rollingstar.studies.reproduce.{paper}")
    if plots_dir is not None:
        Path(plots_dir).mkdir(parents=True, exist_ok=True)
    return module.run(quick=quick, plots_dir=plots_dir, seed=seed)
