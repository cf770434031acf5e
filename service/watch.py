"""`pwm watch DIR`: notice new downlink directories under DIR and submit their ingest, once each.

A directory (a direct child of DIR, not hidden) holds a complete downlink once its manifest.json
is there (a simulated downlink writes it last) or, for deliveries without one, once nothing in it
has changed for quiet_s seconds: no file or folder in it was written, created, renamed or had
its metadata changed since (the newer of mtime and ctime, so that a copy keeping the source's
modification times still counts as a change). Empty directories wait.

A directory written to after it was submitted (a data file that arrived after its label, a
re-transfer of a file cut short) is submitted again once it has been quiet for quiet_s seconds
since: its products that were rejected for how they arrived are then judged again
(service.ingest), and the ingest job, done already, is queued again (service.jobs.reopen_job).

The watcher remembers what it submitted only while it runs; submitting is idempotent (the ingest
job key, workers.tasks.submit_ingest), so a restarted watcher submits everything again and only
what is not done yet, or changed since its ingest started, is enqueued.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"


def last_change(directory: Path) -> float | None:
    """The latest change (s since the epoch) of the directory or anything in it, or None when it
    holds no file."""
    paths = [directory, *directory.rglob("*")]
    if not any(p.is_file() for p in paths[1:]):
        return None
    try:
        stats = [p.lstat() for p in paths]
    except FileNotFoundError:  # renamed or removed while we looked: still changing
        return time.time()
    return max(max(s.st_mtime, s.st_ctime) for s in stats)


def completeness(directory: Path, *, quiet_s: float, now: float | None = None) -> str | None:
    """Why the downlink in `directory` is complete ("manifest" or "quiet"), or None while it is
    not (see the module's docstring). now: s since the epoch (default the current time)."""
    if (directory / MANIFEST_NAME).is_file():
        return "manifest"
    changed = last_change(directory)
    if changed is not None and (time.time() if now is None else now) - changed >= quiet_s:
        return "quiet"
    return None


class Watcher:
    """Submits each complete downlink directory under `root` once, and again when it has changed
    since and been quiet for quiet_s: submit(directory) -> the job key. A submission that raises
    is logged and tried again at the next poll."""

    def __init__(self, root: Path, *, submit: Callable[[Path], str], quiet_s: float) -> None:
        self.root = Path(root).resolve()
        self.submit = submit
        self.quiet_s = quiet_s
        self.submitted: dict[Path, str] = {}
        self.changed: dict[Path, float | None] = {}  # each one's last change when submitted

    def poll(self) -> list[Path]:
        """Look once; the directories submitted this time."""
        now = time.time()
        submitted = []
        for directory in sorted(p for p in self.root.iterdir()
                                if p.is_dir() and not p.name.startswith(".")):
            if directory in self.submitted:
                changed = last_change(directory)
                before = self.changed[directory]
                if changed is None or (before is not None and changed <= before) \
                        or now - changed < self.quiet_s:
                    continue
                reason: str | None = "changed since its submission, then quiet"
            else:
                reason = completeness(directory, quiet_s=self.quiet_s, now=now)
                if reason is None:
                    continue
                changed = last_change(directory)
            try:
                key = self.submit(directory)
            except Exception:
                log.exception("could not submit the ingest of %s; trying again later", directory)
                continue
            self.submitted[directory], self.changed[directory] = key, changed
            submitted.append(directory)
            log.info("%s is complete (%s): ingest submitted as %s", directory, reason, key)
        return submitted


def watch(root: Path, *, submit: Callable[[Path], str], quiet_s: float, poll_s: float,
          once: bool = False) -> None:
    """Poll `root` every poll_s seconds (just once with `once`) and submit the complete downlinks
    (Watcher); runs until interrupted."""
    watcher = Watcher(root, submit=submit, quiet_s=quiet_s)
    log.info("watching %s (complete with %s or %g s quiet; every %g s)", watcher.root,
             MANIFEST_NAME, quiet_s, poll_s)
    while True:
        watcher.poll()
        if once:
            return
        time.sleep(poll_s)
