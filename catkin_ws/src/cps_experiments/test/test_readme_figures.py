"""The README's demo figures are generated from the committed run and agree with it."""

import json

import pytest

from cps_experiments import readme_figures


def test_the_readme_quotes_the_committed_demo_run():
    with open(readme_figures.README) as stream:
        section = readme_figures.readme_section(stream.read())
    assert section == readme_figures.demo_paragraph(), (
        "README.md's demo figures differ from docs/results/demo: run `python -m cps_experiments.readme_figures --write`"
    )


def test_a_figure_that_differs_from_the_run_is_caught(tmp_path):
    for name in ("verdict.json", "scores.json", "report.md"):
        (tmp_path / name).write_bytes(open(f"{readme_figures.DEMO_DIR}/{name}", "rb").read())
    scores = json.loads((tmp_path / "scores.json").read_text())
    scores["f1_exact"] += 0.1
    (tmp_path / "scores.json").write_text(json.dumps(scores))
    assert readme_figures.demo_paragraph(str(tmp_path)) != readme_figures.demo_paragraph()


def test_a_readme_without_the_markers_is_refused():
    with pytest.raises(ValueError, match="demo-figures"):
        readme_figures.readme_section("# no markers here\n")
