"""The recipes of the README and the site (docs/) that need no SocketCAN run as written
(``support.recipes``); the vcan suite runs the others (``test_vcan_readme.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.recipes import recipes, run_session, sessions


def test_the_readme_has_recipes_of_both_kinds() -> None:
    assert sessions("local") and sessions("vcan")


def test_the_parser_reads_a_session_as_a_shell_would() -> None:
    text = (
        "<!-- recipe: s local -->\n```sh\n"
        "canergy keys -o m.key   # a comment\n"
        "python -m firmware_model --nodes 1-5 \\\n    --status-file 'a # b.json' &\n"
        "\n# a whole-line comment\ncanergy grant --control c.sock --node 3 --amount 0.5J\n"
        "```\n```sh\nnot a recipe\n```\n"
    )
    (recipe,) = recipes(text)
    assert (recipe.session, recipe.where, recipe.line) == ("s", "local", 3)
    texts = [(c.text, c.line, c.background) for c in recipe.commands]
    assert texts == [
        ("canergy keys -o m.key", 3, False),
        ("python -m firmware_model --nodes 1-5      --status-file 'a # b.json'", 4, True),
        ("canergy grant --control c.sock --node 3 --amount 0.5J", 8, False),
    ]
    assert recipe.commands[1].waits_for() == ["a # b.json"]


def test_a_failing_recipe_fails_and_names_its_line(tmp_path: Path) -> None:
    text = "<!-- recipe: s local -->\n```sh\ncanergy demo --nodes 0\n```\n"
    with pytest.raises(AssertionError, match=r"README.md:3: canergy demo --nodes 0\nexit 2"):
        run_session(recipes(text), tmp_path)


def test_a_failing_recipe_on_a_site_page_names_that_page(tmp_path: Path) -> None:
    text = "<!-- recipe: s local -->\n```sh\ncanergy demo --nodes 0\n```\n"
    with pytest.raises(AssertionError, match=r"docs/guide/x.md:3: canergy demo --nodes 0"):
        run_session(recipes(text, "docs/guide/x.md"), tmp_path)


def test_recipes_are_read_from_the_readme_and_the_sites_pages() -> None:
    pages = {command.page for recipe in recipes() for command in recipe.commands}
    assert "README.md" in pages and any(page.startswith("docs/guide/") for page in pages)


def test_a_background_command_that_does_not_stop_cleanly_fails(tmp_path: Path) -> None:
    # ends 3 on SIGINT; the harness sees it up once it holds a socket (as a bus's program does)
    loop = (
        "python -c 'import signal, socket, sys, time; "
        "signal.signal(signal.SIGINT, lambda *_: sys.exit(3)); "
        "s = socket.socket(); time.sleep(300)' &"
    )
    text = f"<!-- recipe: s local -->\n```sh\n{loop}\n```\n"
    with pytest.raises(AssertionError, match="exit 3"):
        run_session(recipes(text), tmp_path)


@pytest.mark.parametrize("name", sorted(sessions("local")))
def test_readme_recipe(name: str, tmp_path: Path) -> None:
    run_session(sessions("local")[name], tmp_path)
