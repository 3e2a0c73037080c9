"""The report writer: table cells (missing values, integers, decimals, pipes), model cards
and putting a named section into a card (replace, insert, append; idempotent)."""
import numpy as np
import pytest

from lidar_quality_training.report import (ModelCard, Section, bullets, code_block, fmt,
                                           markdown_table, put_section, update_card)


def test_cells_missing_integers_and_decimals():
    assert [fmt(x) for x in (None, float("nan"), np.nan, float("inf"), -np.inf)] == ["–"] * 5
    assert [fmt(x) for x in (0, 3, np.int64(-12), np.uint8(7))] == ["0", "3", "-12", "7"]
    assert fmt(0.5) == "0.500" and fmt(np.float32(0.25), 1) == "0.2" and fmt(2.0) == "2.000"
    assert fmt(1 / 3, 4) == "0.3333" and fmt(12.5, 0) == "12"
    assert fmt((0.5, 0.01)) == "0.500 ± 0.010" and fmt([1, float("nan")], 2) == "1 ± –"
    assert fmt(True) == "yes" and fmt(np.bool_(False)) == "no"
    assert fmt("3") == "3" and fmt("nan") == "nan"  # text is never read as a number


def test_table_layout_and_digits():
    t = markdown_table(["m", "v", "n"], [["a", float("nan"), 0], ["b", (0.5, 0.01), 3],
                                         ["c", 0.12345, np.int32(40)]], digits=2)
    assert t == ("| m | v | n |\n|---|---|---|\n| a | – | 0 |\n| b | 0.50 ± 0.01 | 3 |\n"
                 "| c | 0.12 | 40 |\n")
    assert markdown_table(["", "x"], [["naive", ""]]) == "| | x |\n|---|---|\n| naive | |\n"
    assert markdown_table(["a"], []) == "| a |\n|---|\n"


def test_table_escapes_pipes_once():
    t = markdown_table(["a|b"], [["`x|y`"], [r"p\|q"]])
    assert t.splitlines() == [r"| a\|b |", "|---|", r"| `x\|y` |", r"| p\|q |"]
    for line in t.splitlines():  # every row has the header's column count
        assert len([c for c in line.replace(r"\|", "").split("|")]) == 3


def test_table_refuses_ragged_rows():
    with pytest.raises(ValueError, match="2 cells under 3 columns"):
        markdown_table(["a", "b", "c"], [[1, 2]])


def _card():
    card = ModelCard("Models", ["What they are."])
    card.section("Data", bullets(["one", "two"]), "")  # an empty block is left out
    card.section("Metrics", markdown_table(["k", "v"], [["auroc", 0.9]]))
    card.section("Reproduce", code_block("train --out m\n# not a heading"))
    card.section("Limits", "Simulated only.")
    return card


def test_model_card_text():
    assert _card().render() == (
        "# Models\n\nWhat they are.\n\n## Data\n\n- one\n- two\n\n## Metrics\n\n"
        "| k | v |\n|---|---|\n| auroc | 0.900 |\n\n## Reproduce\n\n```bash\ntrain --out m\n"
        "# not a heading\n```\n\n## Limits\n\nSimulated only.\n")


def test_put_section_replaces_in_place_and_is_idempotent():
    text = _card().render()
    held = Section("Held-out evaluation", ["AUROC 0.8."])
    once = put_section(text, held, before="Limits")
    assert once.index("## Held-out evaluation") < once.index("## Limits")
    assert "\n\nAUROC 0.8.\n\n## Limits\n" in once
    assert put_section(once, held, before="Limits") == once
    again = put_section(once, Section("Held-out evaluation", ["AUROC 0.7."]), before="Limits")
    assert again == once.replace("AUROC 0.8.", "AUROC 0.7.")
    # A '#' line in a code block is no heading: replacing Reproduce keeps Limits.
    code = put_section(text, Section("Reproduce", [code_block("other")]))
    assert code == text.replace("train --out m\n# not a heading", "other")


def test_put_section_appends_when_absent_and_replaces_the_last():
    text = _card().render()
    held = Section("Held-out evaluation", ["<!-- begin -->\nAUROC 0.8.\n<!-- end -->"])
    once = put_section(text, held, before="No such section")
    assert once == text + "\n## Held-out evaluation\n\n<!-- begin -->\nAUROC 0.8.\n<!-- end -->\n"
    assert put_section(once, held) == once
    assert put_section("", held) == held.render()


def test_update_card_writes_the_file(tmp_path):
    path = tmp_path / "MODEL_CARD.md"
    held = Section("Held-out evaluation", ["AUROC 0.8."])
    update_card(path, held)  # no card yet: the section alone
    assert path.read_text() == "## Held-out evaluation\n\nAUROC 0.8.\n"
    _card().write(path)
    update_card(path, held, before="Limits")
    update_card(path, held, before="Limits")
    text = path.read_text()
    assert text.count("## Held-out evaluation") == 1 and text.count("## Limits") == 1
    assert text.index("## Held-out evaluation") < text.index("## Limits")
