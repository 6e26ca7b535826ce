"""The documentation against the code: docs/parameters.md is the page `mireg param-docs`
generates from the declared parameters."""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_parameters_page_is_the_generated_one():
    from multi_instance_reg.tools.param_docs import parameters_markdown

    assert (ROOT / "docs" / "parameters.md").read_text() == parameters_markdown(), \
        "regenerate: mireg param-docs -o docs/parameters.md"
