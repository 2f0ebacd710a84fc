"""State files in authenticated mode (security second pass, items 8 and 9): a MAC under a key
derived from the master key, the keys' epoch recorded and held to, fresh books refused under keys
that already kept books, and every state file 0600 whatever the umask. The attacks are the
issue's: edit the JSON and recompute the checksum, strip the MAC, bring another key or epoch."""

from __future__ import annotations

import json
import os
import stat
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from support.stderr import without_no_fsync

from canergy.auth.keys import Key, derive_node_key, load_key, new_master
from canergy.auth.state_key import StateKeyError, StateSeal, claim, epochs_record, state_seal
from canergy.cli import main
from canergy.cli import supervisor as supervisor_cli
from canergy.core.gateway import Gateway, GatewayState
from canergy.core.state import Decision, Phase, Session, SupervisorState
from canergy.frozen import evolve
from canergy.live.gateway.state import load_gateway, save_gateway
from canergy.live.supervisor.state_file import (
    BooksWriter,
    StateFileError,
    books_checksum,
    load_state,
    save_state,
)
from canergy.messages import Admit, Commit, Intention

J = 1_000_000
MASTER = new_master(1)
SEAL = state_seal(MASTER)


def _state() -> SupervisorState:
    """10 J initial; node 1 was paid 3 J and returned 0.2 J, node 3 holds a 0.5 J COMMIT."""
    sessions = (
        Session(1, Phase.IDLE, 4, 0, 3 * J, Decision.NONE, 2, 200_000),
        Session(3, Phase.WAIT_CONFIRM, 9, 500_000, J, Decision.COMMIT, 0, 0),
    )
    return SupervisorState(10 * J, 10 * J - 3 * J + 200_000 - 500_000 - J, 0, sessions)


def _saved(tmp_path: Path, seal: StateSeal | None = SEAL) -> Path:
    path = tmp_path / "s.json"
    save_state(path, _state(), "hardened", fsync=False, seal=seal)
    return path


def _rewrite(path: Path, change: Callable[[dict[str, Any]], object]) -> None:
    """What the issue did: edit the books, then recompute the checksum (if any) to match."""
    books = json.loads(path.read_text())
    change(books)
    if "checksum" in books:
        books["checksum"] = books_checksum(books)
    path.write_text(json.dumps(books))


def _load(path: Path, seal: StateSeal | None = SEAL, **kw: Any) -> SupervisorState:
    return load_state(path, "hardened", (1, 3), seal=seal, **kw)


def _more(**fields: int) -> Callable[[dict[str, Any]], None]:
    """Add 1,000 J to each named field (``sessions.1.delivered_uj`` as ``delivered``)."""

    def change(books: dict[str, Any]) -> None:
        for name, joules in fields.items():
            where = books["sessions"]["1"] if name == "delivered" else books
            key = "delivered_uj" if name == "delivered" else f"{name}_uj"
            where[key] += joules * J

    return change


# Edits that keep every check of the books (they balance) but the MAC: the issue's three.
BALANCED_EDITS = {
    "initial": _more(initial=1000, usable=1000),  # +1,000 J initial, granted out of "10 J"
    "delivered": _more(delivered=1000, initial=1000),  # pays node 1 1,000 J in one intention
    "injected": _more(injected=1000, usable=1000),
}


# -- the seal --------------------------------------------------------------------------------


def test_a_sealed_file_records_its_epoch_and_loads_as_saved(tmp_path: Path) -> None:
    books = json.loads(_saved(tmp_path).read_text())
    assert books["epoch"] == 1 and books["mac"].startswith("cmac:") and len(books["mac"]) == 37
    assert _load(tmp_path / "s.json") == _state()
    assert "secret" not in repr(SEAL) and MASTER.secret.hex() not in repr(SEAL)


@pytest.mark.parametrize("edit", sorted(BALANCED_EDITS))
def test_an_edit_with_its_checksum_recomputed_is_refused(tmp_path: Path, edit: str) -> None:
    path = _saved(tmp_path)
    _rewrite(path, BALANCED_EDITS[edit])
    books = json.loads(path.read_text())
    assert books["checksum"] == books_checksum(books)  # what the checksum alone would take
    with pytest.raises(StateFileError) as exc:
        _load(path)
    message = str(exc.value)
    assert message.startswith(f"{path}: mac: the MAC does not match the books"), message
    assert "--accept-edited-state" in message and "\n" not in message


@pytest.mark.parametrize(
    "strip", [("mac",), ("mac", "epoch"), ("mac", "epoch", "checksum")], ids="-".join
)
def test_a_stripped_mac_is_refused(tmp_path: Path, strip: tuple[str, ...]) -> None:
    """Stripping the MAC (and the epoch) makes a file of the unauthenticated kind: in
    authenticated mode that is refused as firmly as a wrong MAC, edited or not."""
    path = _saved(tmp_path)

    def change(books: dict[str, Any]) -> None:
        BALANCED_EDITS["initial"](books)
        for field in strip:
            books.pop(field, None)

    _rewrite(path, change)
    with pytest.raises(StateFileError, match=r": (mac: no MAC|checksum: no checksum)"):
        _load(path)


def test_another_master_key_is_refused(tmp_path: Path) -> None:
    path = _saved(tmp_path)
    with pytest.raises(StateFileError, match="sealed with another master key"):
        _load(path, state_seal(new_master(1)))


def test_the_seal_is_per_epoch_and_identity() -> None:
    """The same master gives a key per epoch and per gateway, none of them a node's key."""
    keys = {
        "supervisor": state_seal(MASTER).mac(b"x"),
        "epoch 2": state_seal(Key("master", 2, MASTER.secret)).mac(b"x"),
        "gateway 1": state_seal(MASTER, 1).mac(b"x"),
        "gateway 2": state_seal(MASTER, 2).mac(b"x"),
    }
    assert len(set(keys.values())) == len(keys)
    node_key = derive_node_key(MASTER.secret, 1, 1)
    assert StateSeal(node_key, 1).mac(b"x") not in keys.values()
    assert state_seal(MASTER).mac(b"x") == keys["supervisor"]  # derived, not random


@pytest.mark.parametrize("flag", [False, True])
def test_books_of_another_epoch_are_refused_even_with_the_flag(tmp_path: Path, flag: bool) -> None:
    path = _saved(tmp_path)
    epoch_2 = state_seal(Key("master", 2, MASTER.secret))
    with pytest.raises(StateFileError) as exc:
        _load(path, epoch_2, accept_edited=flag)
    message = str(exc.value)
    assert (
        "epoch: the books were begun under keys of epoch 1, but --auth gives keys of epoch 2"
        in (message)
    )
    assert "keys of a new epoch need a new state file" in message, message
    _rewrite(path, lambda books: books.update(epoch=2))  # the epoch edited to the key's
    with pytest.raises(StateFileError, match="mac: the MAC does not match"):
        _load(path, epoch_2)


@pytest.mark.parametrize(
    ("value", "why"),
    [(-1, "-1 is negative"), (2**32, "is above 4294967295"), ("1", "is a string"), (1.5, "")],
)
def test_a_bad_epoch_is_named(tmp_path: Path, value: object, why: str) -> None:
    path = _saved(tmp_path)
    _rewrite(path, lambda books: books.update(epoch=value))
    with pytest.raises(StateFileError, match=f"epoch: .*{why}"):
        _load(path, accept_edited=True)


@pytest.mark.parametrize("mac", [12, None, "cmac:00", "cmac:é" * 8, "cmac:\ud800", ["cmac:"], ""])
def test_a_mac_of_any_other_shape_is_refused(tmp_path: Path, mac: object) -> None:
    path = _saved(tmp_path)
    _rewrite(path, lambda books: books.update(mac=mac))
    with pytest.raises(StateFileError, match="mac: "):
        _load(path)


def test_the_flag_takes_an_edited_file_with_a_warning_and_seals_it_again(tmp_path: Path) -> None:
    path = _saved(tmp_path)
    _rewrite(path, BALANCED_EDITS["initial"])
    heard: list[str] = []
    state = _load(path, accept_edited=True, on_edited=heard.append)
    assert state.initial == 1010 * J
    assert len(heard) == 1 and "the MAC does not match" in heard[0]
    assert "the next save writes a fresh checksum and MAC" in heard[0]
    save_state(path, state, "hardened", fsync=False, seal=SEAL)
    assert _load(path) == state


def test_an_unsealed_file_needs_the_flag_once_in_authenticated_mode(tmp_path: Path) -> None:
    """A file from before authenticated mode (or one stripped) is taken only with the flag;
    the next save seals it, and from then on it loads without."""
    path = _saved(tmp_path, seal=None)
    with pytest.raises(StateFileError, match="mac: no MAC"):
        _load(path)
    heard: list[str] = []
    state = _load(path, accept_edited=True, on_edited=heard.append)
    assert len(heard) == 1 and "no MAC" in heard[0]
    BooksWriter(path, "hardened", fsync=False, seal=SEAL).save(state)
    assert _load(path) == state


def test_a_sealed_file_without_its_key_needs_the_flag(tmp_path: Path) -> None:
    """Dropping --auth must not make the MAC optional: the key is what checks it."""
    path = _saved(tmp_path)
    with pytest.raises(StateFileError, match="mac: sealed in authenticated mode, and without"):
        _load(path, None)
    assert _load(path, None, accept_edited=True) == _state()


def test_an_older_copy_of_the_same_books_still_passes(tmp_path: Path) -> None:
    """The residual risk the docs give: a MAC shows who wrote the books, not that they are the
    last ones written. A copy from before node 1 was paid loads, MAC and all."""
    path = _saved(tmp_path)
    older = path.read_bytes()
    node_1, node_3 = _state().sessions
    paid = evolve(node_1, tx=5, delivered=node_1.delivered + J)
    later = evolve(_state(), usable=_state().usable - J, sessions=(paid, node_3))
    save_state(path, later, "hardened", fsync=False, seal=SEAL)
    path.write_bytes(older)
    assert _load(path) == _state()


# -- file modes ------------------------------------------------------------------------------


@pytest.fixture
def renamed_modes(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[int]]:
    """Under umask 000: the mode of every temporary at the moment it replaces a file."""
    modes: list[int] = []
    replace = os.replace

    def spy(src: Any, dst: Any) -> None:
        modes.append(stat.S_IMODE(os.stat(src).st_mode))
        replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    old = os.umask(0)
    try:
        yield modes
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("seal", [None, SEAL], ids=["checksum", "mac"])
def test_state_files_are_0600_whatever_the_umask(
    tmp_path: Path, renamed_modes: list[int], seal: StateSeal | None
) -> None:
    books = tmp_path / "s.json"
    books.write_text("{}")
    books.chmod(0o666)  # an old file open to all: replaced by a private one
    stale = tmp_path / f".s.json.{os.getpid()}.tmp"  # a crashed save's temporary, open to all
    stale.write_text("")
    stale.chmod(0o666)
    save_state(books, _state(), "hardened", fsync=False, seal=seal)
    gateway = tmp_path / "gw.json"
    save_gateway(gateway, _gateway(), "hardened", fsync=True, seal=seal)
    assert renamed_modes == [0o600, 0o600]
    assert _mode(books) == _mode(gateway) == 0o600
    os.umask(0o777)  # nothing for the owner either: still 0600, and readable
    save_state(books, _state(), "hardened", fsync=False, seal=seal)
    assert _mode(books) == 0o600 and _load(books, seal) == _state()


# -- a gateway's state file ------------------------------------------------------------------

GW = 20
GW_SEAL = state_seal(MASTER, GW)


def _gateway() -> GatewayState:
    """Credited 2 J upstream, 1 J of it reserved for node 2 below."""
    gw = Gateway(GW, (1, 2, 3))
    gw.books_lost(1, 0)
    gw.receive_upstream(Admit(GW, 1, 0, 0), 0)
    gw.receive_upstream(Intention(GW, 1, 2000, 0), 0)
    gw.receive_upstream(Commit(GW, 1, 2000), 0)
    gw.down.begin(2, J, 0)
    return gw.state


def _load_gateway(path: Path, seal: StateSeal | None = GW_SEAL, **kw: Any) -> GatewayState:
    return load_gateway(path, "hardened", GW, (1, 2, 3), seal=seal, **kw)


def _gateway_edit(books: dict[str, Any]) -> None:
    """50 J more from above, all of it usable below: the roles still agree."""
    books["upstream"]["credited_uj"] += 50 * J
    books["upstream"]["spent_uj"] += 50 * J
    books["downstream"]["injected_uj"] += 50 * J
    books["downstream"]["usable_uj"] += 50 * J


def test_a_gateway_file_is_sealed_for_its_own_identity(tmp_path: Path) -> None:
    path = tmp_path / "gw.json"
    save_gateway(path, _gateway(), "hardened", fsync=False, seal=GW_SEAL)
    assert json.loads(path.read_text())["epoch"] == 1
    assert _load_gateway(path) == _load_gateway(path, None, accept_edited=True)
    with pytest.raises(StateFileError, match="mac: the MAC does not match"):
        _load_gateway(path, state_seal(MASTER, GW + 1))  # another gateway's key
    with pytest.raises(StateFileError, match="mac: the MAC does not match"):
        _load_gateway(path, SEAL)  # the supervisor's key
    with pytest.raises(StateFileError, match="epoch: the books were begun under keys of epoch"):
        _load_gateway(path, state_seal(Key("master", 7, MASTER.secret), GW))


def test_a_gateway_file_edited_or_stripped_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "gw.json"
    save_gateway(path, _gateway(), "hardened", fsync=False, seal=GW_SEAL)
    _rewrite(path, _gateway_edit)
    with pytest.raises(StateFileError, match="mac: the MAC does not match"):
        _load_gateway(path)
    _rewrite(path, lambda books: [books.pop(k) for k in ("mac", "epoch")])
    with pytest.raises(StateFileError, match="mac: no MAC"):
        _load_gateway(path)
    heard: list[str] = []
    taken = _load_gateway(path, accept_edited=True, on_edited=heard.append)
    assert taken.down.usable == _gateway().down.usable + 50 * J and len(heard) == 1


def test_a_gateway_file_with_a_number_no_field_takes_is_refused_not_crashed(
    tmp_path: Path,
) -> None:
    path = tmp_path / "gw.json"
    save_gateway(path, _gateway(), "hardened", fsync=False)
    path.write_text(path.read_text().replace('"last_tx":1', '"last_tx":1e30'))
    with pytest.raises(StateFileError, match="last_tx: 1e30 is not an integer"):
        load_gateway(path, "hardened", GW, (1, 2, 3), accept_edited=True)


# -- the epochs record -----------------------------------------------------------------------


def test_fresh_books_under_keys_that_kept_books_are_refused(tmp_path: Path) -> None:
    key_path = tmp_path / "m.key"
    books = tmp_path / "s.json"
    record = claim(key_path, SEAL, books, fresh=True)
    assert not epochs_record(key_path).exists()  # nothing is written before the first save
    record()
    assert _mode(epochs_record(key_path)) == 0o600
    claim(key_path, SEAL, books, fresh=False)()  # the same books again: fine, listed once
    assert len(epochs_record(key_path).read_text().splitlines()) == 1
    for other in (books, tmp_path / "other.json"):
        with pytest.raises(StateKeyError, match="already began books"):
            claim(key_path, SEAL, other, fresh=True)
    claim(key_path, state_seal(new_master(1)), books, fresh=True)()  # a new key: new books
    claim(key_path, GW_SEAL, books, fresh=True)()  # a gateway's own books under the master


def test_a_torn_record_line_hides_no_later_claim(tmp_path: Path) -> None:
    key_path = tmp_path / "m.key"
    epochs_record(key_path).write_text("0123")  # a crash in the middle of a line
    claim(key_path, SEAL, tmp_path / "s.json", fresh=True)()
    with pytest.raises(StateKeyError, match="already began books"):
        claim(key_path, SEAL, tmp_path / "s.json", fresh=True)


def test_a_record_that_is_no_file_is_refused(tmp_path: Path) -> None:
    os.mkfifo(epochs_record(tmp_path / "m.key"))
    with pytest.raises(StateKeyError, match="not a regular file"):
        claim(tmp_path / "m.key", SEAL, tmp_path / "s.json", fresh=True)


def test_an_unwritable_record_is_refused_before_anything_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "access", lambda path, mode: False)  # root may write anywhere
    with pytest.raises(StateKeyError, match="cannot write the epochs record"):
        claim(tmp_path / "m.key", SEAL, tmp_path / "s.json", fresh=True)


# -- through the command line ----------------------------------------------------------------


class Cli:
    """``canergy supervisor`` runs whose loop is replaced: each starts, reports once and ends."""

    def __init__(self, tmp: Path, capsys: pytest.CaptureFixture[str]) -> None:
        self.tmp = tmp
        self.capsys = capsys
        self.status: list[dict[str, Any]] = []

    def keys(self, name: str, epoch: int = 1) -> Path:
        path = self.tmp / name
        assert main(["keys", "-o", str(path), "--epoch", str(epoch)]) == 0
        return path

    def supervisor(self, *extra: str, state: str = "s.json") -> tuple[int, str]:
        bus = ["-i", "virtual", "-c", f"mac-{uuid.uuid4().hex}", "--nodes", "1-3"]
        self.capsys.readouterr()
        code = main(["supervisor", *bus, "--state", str(self.tmp / state), "--no-fsync", *extra])
        return code, without_no_fsync(self.capsys.readouterr().err)


@pytest.fixture
def cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> Cli:
    runs = Cli(tmp_path, capsys)
    monkeypatch.setattr(
        supervisor_cli,
        "serve_supervisor",
        lambda runtime, service, *a, **kw: runs.status.append(service.status()),
    )
    return runs


def test_the_supervisor_seals_its_books_and_refuses_the_issue_edit(cli: Cli) -> None:
    master = cli.keys("m.key")
    path = cli.tmp / "s.json"
    assert cli.supervisor("--auth", str(master)) == (0, "")
    books = json.loads(path.read_text())
    assert books["epoch"] == 1 and "mac" in books and _mode(path) == 0o600
    _rewrite(path, BALANCED_EDITS["initial"])
    before = path.read_bytes()
    code, err = cli.supervisor("--auth", str(master))
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{path}: mac: the MAC does not match the books" in err
    assert path.read_bytes() == before and len(cli.status) == 1  # refused before any write
    code, err = cli.supervisor("--auth", str(master), "--accept-edited-state")
    assert code == 0 and "warning" in err and "taken as it is" in err, err
    assert cli.status[-1]["initial_uj"] == 1010 * J
    seal = state_seal(load_key(master))
    assert load_state(path, "hardened", (1, 2, 3), seal=seal).initial == 1010 * J  # sealed again


def test_the_supervisor_refuses_keys_of_another_epoch(cli: Cli) -> None:
    assert cli.supervisor("--auth", str(cli.keys("m1.key")))[0] == 0
    for flags in ((), ("--accept-edited-state",)):
        code, err = cli.supervisor("--auth", str(cli.keys(f"m2{len(flags)}.key", 2)), *flags)
        assert code == 2 and "epoch: the books were begun under keys of epoch 1" in err, err


def test_a_supervisor_without_its_books_refuses_keys_that_kept_books(cli: Cli) -> None:
    master = cli.keys("m.key")
    assert cli.supervisor("--auth", str(master)) == (0, "")
    (cli.tmp / "s.json").unlink()  # the books lost: the counters would start again
    for state in ("s.json", "new.json"):
        code, err = cli.supervisor("--auth", str(master), state=state)
        assert code == 2 and "already began books" in err and "--epoch" in err, err
        assert not (cli.tmp / state).exists()
    assert cli.supervisor("--auth", str(cli.keys("m2.key", 2))) == (0, "")  # a new epoch


def test_a_run_that_never_saved_claims_no_keys(cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bus that will not open, or --listen-only, begins no books: the keys stay free."""
    master = cli.keys("m.key")

    def no_bus(*args: Any, **kw: Any) -> Any:
        raise OSError("no such bus")

    with monkeypatch.context() as patched:
        patched.setattr(supervisor_cli, "open_bus", no_bus)
        assert cli.supervisor("--auth", str(master))[0] == 2
    assert cli.supervisor("--auth", str(master), "--listen-only")[0] == 0
    assert not (cli.tmp / "s.json").exists() and not epochs_record(master).exists()
    assert cli.supervisor("--auth", str(master)) == (0, "")
    assert epochs_record(master).exists()


def test_without_a_key_the_file_keeps_its_checksum_only(cli: Cli) -> None:
    assert cli.supervisor() == (0, "")
    books = json.loads((cli.tmp / "s.json").read_text())
    assert "mac" not in books and "epoch" not in books and books["checksum"].startswith("sha")
    code, err = cli.supervisor("--auth", str(cli.keys("m.key")))
    assert code == 2 and "mac: no MAC" in err and "--accept-edited-state" in err, err
