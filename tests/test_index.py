"""The results summary (ablate.tables.index): one line per table, read from its markdown and its spec, spliced
between markers and nowhere else."""

from omegaconf import OmegaConf

from ablate.tables.index import BEGIN, END, paper_top, summarise_table, write_index

SPEC = OmegaConf.create(
    {
        "name": "t2",
        "title": "Table II",
        "primary": "det_rate",
        "rows": [
            {"row": "chinet", "name": "ChiNet", "paper": {"det_rate": 97.35}},
            {"row": "unet", "name": "U-Net", "paper": {"det_rate": 94.2}},
            {"row": "other", "name": "Other [9]", "paper_only": True, "paper": {"det_rate": 99.0}},
        ],
    }
)


def footer(top: str, verdict: str) -> str:
    return (
        "Kendall τ between our ranking and the paper's on Det. Rate %: 1.00 over 2 rows.\n"
        f"Top row {top} against the second, U-Net, on Det. Rate %: +1.20 [+0.10, +2.30], paired t, p = 0.040: "
        f"{verdict}.\nmore text"
    )


def test_the_papers_top_row_leaves_out_systems_not_run_here():
    assert paper_top(SPEC) == "ChiNet"
    assert paper_top(OmegaConf.create({"name": "f", "primary": "ap", "rows": [{"row": "a", "paper": {}}]})) is None


def test_the_headline_holds_only_for_the_papers_top_row_ahead_beyond_noise():
    assert summarise_table(SPEC, footer("ChiNet", "ahead beyond seed noise")).headline == "holds"
    assert summarise_table(SPEC, footer("ChiNet", "not separable from seed noise")).headline == (
        "not separable from seed noise"
    )
    line = summarise_table(SPEC, footer("U-Net", "ahead beyond seed noise"))
    assert line.headline == "does not hold" and line.ours == "U-Net" and line.paper == "ChiNet"
    assert line.tau == "1.00 (2 rows)"
    assert summarise_table(SPEC, "No finished runs yet.").headline == "undecided (too few seeds)"


def test_the_summary_goes_between_the_markers_and_nowhere_else(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "t2.md").write_text(footer("ChiNet", "ahead beyond seed noise"))
    (results / "README.md").write_text(f"# results\n\nkept\n\n{BEGIN}\nthe previous summary\n{END}\n\nkept too\n")
    readme = tmp_path / "README.md"
    readme.write_text("no markers here\n")
    assert write_index([SPEC], results, readme) == [results / "README.md"]
    text = (results / "README.md").read_text()
    assert text.startswith("# results\n\nkept\n\n") and text.endswith(f"{END}\n\nkept too\n") and "previous" not in text
    assert "| [t2](t2.md) | ChiNet | ChiNet | 1.00 (2 rows) | holds |" in text
    assert readme.read_text() == "no markers here\n"
