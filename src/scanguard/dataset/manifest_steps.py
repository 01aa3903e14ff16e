"""What the manifest of a build directory says after each step of a build.

Each function here computes the new manifest from the one on disk; the callers apply them
under the manifest lock (`scanguard.dataset.manifest.update_manifest`), so concurrent builds
into one directory (simulated and ``--recording`` ones) keep each other's entries and
pending work.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from scanguard.dataset.config import DatasetConfig
from scanguard.dataset.manifest import update_manifest
from scanguard.dataset.planning import PlannedSequence, RecordingJob
from scanguard.dataset.shards import (
    FORMAT,
    FORMAT_VERSION,
    inspect_shard,
    sequence_file,
    warn_corrupt,
)
from scanguard.dataset.store import MANIFEST, read_manifest
from scanguard.errors import ConfigError

log = logging.getLogger(__name__)


def _simulated_fields(
    config: DatasetConfig, entries: list[dict[str, Any]], pending: list[dict[str, Any]]
) -> dict[str, Any]:
    """The manifest fields a simulated build owns."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": config.name,
        "config_fingerprint": config.fingerprint(),
        "matcher": config.matcher,
        "initial_guess": config.initial_guess,
        "labels": config.labels.model_dump(mode="json"),
        "complete": not pending,
        "pending": pending,
        "sequences": entries,
    }


def _is_recording_entry(out: Path, entry: dict[str, Any]) -> bool:
    """An entry added by a ``--recording`` build (older ones are known by their metadata)."""
    if "recording" in entry:
        return True
    state = inspect_shard(out / entry["file"], entry["file"])
    return state.ok and "recording" in state.meta


def simulated_manifest(
    current: dict[str, Any],
    out: Path,
    config: DatasetConfig,
    plan: list[PlannedSequence],
    done: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """The manifest after a step of a simulated build, keeping what other builds added.

    Entries of recordings (and anything else not in the plan whose file exists) are kept
    after the planned sequences; when the directory held another simulated config (rebuilt
    with ``overwrite``) its sequences that are not in the new plan are dropped. Work pending
    in other builds (recordings) stays pending.
    """
    planned = {p.sequence for p in plan}
    replaced = current.get("config_fingerprint") not in (None, config.fingerprint())
    others = []
    for e in current.get("sequences", []):
        if e.get("sequence") in planned:
            continue
        if replaced and not _is_recording_entry(out, e):
            continue
        if not (out / e["file"]).is_file():
            log.warning("%s: listed in the manifest but missing; dropped", out / e["file"])
            continue
        others.append(e)
    # work other builds registered (recordings, merged sources) stays pending
    pending = [x for x in current.get("pending", []) if "recording" in x or "source" in x]
    pending += [{"sequence": p.sequence} for p in plan if p.sequence not in done]
    entries = [done[p.sequence] for p in plan if p.sequence in done] + others
    new = dict(current)
    new.update(_simulated_fields(config, entries, pending))
    new["kind"] = "mixed" if others else "simulated"
    return new


def recordings_manifest(
    current: dict[str, Any],
    out: Path,
    *,
    add_pending: Sequence[dict[str, Any]] = (),
    drop_pending: str | None = None,
    entry: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The manifest after a step of a recording build (under the manifest lock).

    Args:
        current: The manifest on disk.
        out: Build directory.
        add_pending: Pending items to (re)register; older items of the same fingerprint
            are replaced.
        drop_pending: Remove the pending item with this fingerprint (the recording is done
            or failed for good).
        entry: Put this entry in place of the entry of the same sequence (or append it).
    """
    new = dict(current)
    fps = {x["fingerprint"] for x in add_pending}
    if drop_pending is not None:
        fps.add(drop_pending)
    pending = [x for x in current.get("pending", []) if x.get("fingerprint") not in fps]
    pending += list(add_pending)
    entries = list(current.get("sequences", []))
    if entry is not None:
        at = [i for i, e in enumerate(entries) if e.get("sequence") == entry["sequence"]]
        if at:
            entries[at[0]] = entry
        else:
            entries.append(entry)
    new["sequences"] = entries
    new["pending"] = pending
    new["complete"] = not pending
    new.setdefault("name", out.name)
    new["kind"] = "recordings" if "config_fingerprint" not in current else "mixed"
    return new


def find_built(
    out: Path, job: RecordingJob, entries: list[dict[str, Any]], overwrite: bool
) -> str | None:
    """The sequence this recording is already stored as, or None (corrupt files reported).

    A file built before content identity (same file name and options) is kept with a
    warning, unless ``overwrite`` asks to rebuild it.
    """
    for e in entries:
        if e.get("fingerprint") == job.fingerprint:
            path = out / e["file"]
            state = inspect_shard(path, e["file"])
            if state.ok and state.fingerprint == job.fingerprint:
                return str(e["sequence"])
            if path.exists():
                warn_corrupt(path, state)
        elif not overwrite and "fingerprint" not in e and e.get("split") == "heldout":
            state = inspect_shard(out / e["file"], e["file"])
            if state.ok and state.fingerprint == job.legacy:
                log.warning(
                    "%s: built before recordings were identified by content; kept as %s "
                    "without checking that the recording is unchanged (--overwrite rebuilds it)",
                    job.path,
                    e["sequence"],
                )
                return str(e["sequence"])
    return None


def claim_name(
    current: dict[str, Any], out: Path, job: RecordingJob, base: str, overwrite: bool
) -> tuple[str, dict[str, Any] | None]:
    """Choose the sequence name of a recording (under the manifest lock).

    The same recording (same resolved path) built from other content is rebuilt under its
    old name (stale pairs replaced); with other options it is refused unless ``overwrite``.
    A different recording with a name already taken gets ``<name>_<first 8 hex of its
    hash>``. An unlisted file of the same identity (a build killed before its manifest
    update) is adopted.

    Returns:
        The name, and the entry of an adopted file (None: build it).

    Raises:
        ConfigError: The recording was built here with other settings (not ``overwrite``).
    """
    entries = current.get("sequences", [])
    for e in entries:
        if e.get("fingerprint") == job.fingerprint:
            return str(e["sequence"]), None  # its file is corrupt (reported): rebuild
    for e in entries:
        if e.get("recording") != job.source:
            continue
        if e.get("options_fingerprint") == job.options:
            log.warning(
                "%s: the recording changed since it was built into %s; rebuilding it (its "
                "stale pairs are replaced)",
                job.path,
                out / e["file"],
            )
        elif not overwrite:
            raise ConfigError(
                f"{out / e['file']}: built from {job.path} with other settings; use another "
                "output directory or --overwrite"
            )
        return str(e["sequence"]), None
    by_seq = {str(e.get("sequence")): e for e in entries}
    reserved = {
        str(x["sequence"])
        for x in current.get("pending", [])
        if "sequence" in x and x.get("fingerprint") != job.fingerprint
    }
    candidates = [base, f"{base}_{job.digest[:8]}", f"{base}_{job.digest[:16]}"]
    for cand in candidates:
        if cand in reserved:
            continue
        rel = sequence_file(cand)
        e = by_seq.get(cand)
        if e is None:
            state = inspect_shard(out / rel, rel) if (out / rel).exists() else None
            if state is not None and state.ok and state.fingerprint == job.fingerprint:
                assert state.entry is not None
                return cand, {**state.entry, **job.entry_fields()}
            return cand, None  # free, or an orphan of an interrupted build: replaced
        if "recording" in e:
            continue  # another recording's name
        state = inspect_shard(out / e["file"], e["file"])
        if not state.ok:
            warn_corrupt(out / e["file"], state)
            return cand, None
        old = state.meta.get("recording")
        if old is not None and Path(str(old)).name == job.path.name:
            # built before content identity from a file of this name: the same recording
            if not overwrite:
                raise ConfigError(
                    f"{out / e['file']}: built with other settings; use another output "
                    "directory or --overwrite"
                )
            return cand, None
    raise ConfigError(
        f"{out}: no free sequence name for {job.path} (tried {', '.join(candidates)})"
    )


def manifest_entries(out: Path) -> list[dict[str, Any]]:
    """The entries of ``out``'s manifest (none when there is no manifest yet)."""
    return list(read_manifest(out)["sequences"]) if (out / MANIFEST).exists() else []


def drop_pending(out: Path, job: RecordingJob) -> None:
    """Take a recording off the manifest's pending work (done, or failed for good)."""
    update_manifest(
        out, functools.partial(recordings_manifest, out=out, drop_pending=job.fingerprint)
    )


def order_new_entries(
    current: dict[str, Any], before: set[str], order: dict[str, int]
) -> dict[str, Any]:
    """The manifest with the entries added since ``before`` sorted by ``order`` (in place)."""
    entries = list(current.get("sequences", []))
    slots = [i for i, e in enumerate(entries) if str(e.get("sequence")) not in before]
    new = sorted(
        (entries[i] for i in slots), key=lambda e: order.get(str(e.get("sequence")), len(order))
    )
    for i, e in zip(slots, new, strict=True):
        entries[i] = e
    return {**current, "sequences": entries}
