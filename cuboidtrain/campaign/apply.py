"""What a lease sent back, taken into campaign/: the state's parts, the manifest, the log's row.

Once per lease: a lease is applied only onto the state it resumed (its row's `base`, the
manifest's digest then) and as the log's next row, so applying it twice, or an older lease over
a newer one, is refused in one line. Every part is checked against its SHA-256 before anything
in campaign/ changes.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from cuboidtrain.campaign.evaluation import SHIPPED_EVAL, evaluation_record
from cuboidtrain.campaign.lease import EVAL, LEASE
from cuboidtrain.campaign.state import MANIFEST, ShapeState, append_log, read_log, read_state, state_digest, write_manifest
from cuboidtrain.models.zoo import git_commit
from shared.errors import UsageError
from shared.files import write_json


def find_lease(returned: Path) -> Path:
    """The folder holding lease.json: `returned` itself or a folder below it (the device's files_at)."""
    found = sorted(Path(returned).glob(LEASE)) + sorted(Path(returned).glob(f"*/{LEASE}")) \
        + sorted(Path(returned).glob(f"*/*/{LEASE}"))
    if not found:
        raise UsageError(f"{returned}: no {LEASE} in it or in the folders below: not what a lease returns")
    if len(found) > 1:
        raise UsageError(f"{returned}: {len(found)} leases in it ({', '.join(map(str, found))}): apply one folder at a time")
    return found[0].parent


def apply_lease(returned: Path, campaign: Path) -> dict:
    """The lease's row, once campaign/ holds its state and log; UsageError (nothing changed) otherwise."""
    folder, campaign = find_lease(returned), Path(campaign)
    record = json.loads((folder / LEASE).read_text())
    row, entries = record["row"], {s: ShapeState.from_dict(e) for s, e in record["state"].items()}
    applied = len(read_log(campaign))
    if row["lease"] != applied + 1 or row["base"] != state_digest(campaign):
        raise UsageError(f"{folder}: lease {row['lease']} resumed state {row['base']}, but {campaign} holds "
                         f"{applied} leases and state {state_digest(campaign)}: already applied, or a newer lease "
                         f"was; nothing changed")
    for entry in entries.values():
        check_parts(folder, entry)
    # the parts first, then the manifest that names them, then the row: a cut leaves a mismatch restore refuses
    old = {p for e in _current(campaign).values() for p in e.parts}
    for entry in entries.values():
        for part in entry.parts:
            shutil.copyfile(folder / part, campaign / part)
    write_manifest(campaign, entries)
    for stale in old - {p for e in entries.values() for p in e.parts}:
        (campaign / stale).unlink(missing_ok=True)
    if row.get("commit") is None:  # the lent machine has no .git: the commit applied onto is the one it ran
        row["commit"] = git_commit()
    append_log(campaign, row)
    keep_shipped_figures(folder, campaign)
    keep_evaluation(folder, campaign, row, entries)
    return row


def check_parts(folder: Path, entry: ShapeState) -> None:
    digest = hashlib.sha256()
    for part in entry.parts:
        if not (folder / part).is_file():
            raise UsageError(f"{folder / part}: missing ({entry.shape}'s state has {len(entry.parts)} parts); nothing changed")
        digest.update((folder / part).read_bytes())
    if digest.hexdigest() != entry.sha256:
        raise UsageError(f"{folder}: {entry.shape}'s parts do not join into the checkpoint {LEASE} names "
                         f"(SHA-256 differs: a part was damaged in transfer); nothing changed")


def _current(campaign: Path) -> dict[str, ShapeState]:
    return read_state(campaign) if (campaign / MANIFEST).is_file() else {}


def keep_shipped_figures(folder: Path, campaign: Path) -> None:
    """The shipped models' figures measured by this lease, kept so that later leases need not measure them."""
    if not (folder / EVAL).is_file() or (campaign / SHIPPED_EVAL).is_file():
        return
    shipped = json.loads((folder / EVAL).read_text()).get("shipped")
    if shipped:
        write_json(campaign / SHIPPED_EVAL, shipped, indent=1)


def keep_evaluation(folder: Path, campaign: Path, row: dict, entries: dict[str, ShapeState]) -> None:
    """The lease's own evaluation as campaign/eval.json, the newest of the standing state; a lease without
    one leaves the older file, which names its lease (`cuboidtrain campaign evaluate` scores this one)."""
    if not (folder / EVAL).is_file() or not isinstance(row.get("eval"), dict) or "failed" in row["eval"]:
        return
    scored = json.loads((folder / EVAL).read_text())
    steps = {shape: [entry.phase, entry.step] for shape, entry in entries.items()}
    write_json(campaign / EVAL, evaluation_record(row["lease"], steps, row["device"], row["date"], row["eval"], scored),
               indent=1)
