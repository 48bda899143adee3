"""README's install paragraph says what `make setup` installs: every extra of the Makefile's editable install
and every package it installs beside it."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup_recipe() -> str:
    text = (ROOT / "Makefile").read_text()
    return text[text.index("$(STAMP):"):text.index("\ntest:")]


def test_readme_lists_what_make_setup_installs():
    recipe = _setup_recipe()
    (extras,) = re.findall(r"pip install -e '\.\[([a-z,]+)\]'", recipe)
    others = re.findall(r"pip install (?:--no-deps )?([A-Za-z0-9_-]+)==", recipe)    # torch, lpips
    readme = (ROOT / "README.md").read_text()
    para = readme[readme.index("From a checkout: `make setup`"):]
    para = para[:para.index("\n\n")]
    for extra in extras.split(","):
        assert f"`{extra}`" in para, f"README's make setup paragraph does not name the {extra!r} extra"
    for pkg in others:
        assert pkg in para, f"README's make setup paragraph does not name {pkg}"
    assert re.search(r"\d\.\d+ GB for the `make setup`", para)
    for doc in ("docs/install.md", "docs/contributing.md"):
        assert f"ev3dgs[{extras}]" in (ROOT / doc).read_text(), doc
