"""Each downlink's outcome: how many of its products were accepted, rejected or in conflict, its
lidar products and their shots, its kernels, the files it offered that are not used, and how
often it was delivered; the one source of `pwm downlinks` and the API's /downlinks. Also what
`pwm downlinks` says of the catalog as a whole: the maplets whose current revision was made with
another refinement configuration, which no downlink re-refines unless asked
(service.refinement.stale_maplets)."""

from __future__ import annotations

import enum
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from pwm.config import RefinementConfig
from service.rows import (
    Acceptance,
    Downlink,
    DownlinkFile,
    DownlinkStatus,
    Image,
    ImageStatus,
    Kernel,
    LidarProduct,
    Maplet,
    MapletRevision,
)


class Outcome(enum.StrEnum):
    """What a finished ingest made of a downlink's products: all accepted, some, none
    (rejected: every product failed), or it offered none (empty); pending while it is not
    ingested."""

    ACCEPTED = "accepted"
    PARTIAL = "partial"
    REJECTED = "rejected"
    EMPTY = "empty"
    PENDING = "pending"


@dataclass(frozen=True)
class DownlinkSummary:
    id: int
    name: str
    path: str
    received_at: datetime
    status: DownlinkStatus
    repeat_count: int
    last_seen_at: datetime | None
    kernels: int
    images: dict[ImageStatus, int] = field(default_factory=dict)
    unused_files: int = 0
    model_note: str | None = None
    pose_adjustment: dict | None = None
    # its lidar products by status, and the shots (all, and usable) of those accepted
    lidar: dict[Acceptance, int] = field(default_factory=dict)
    lidar_shots: int = 0
    lidar_valid_shots: int = 0

    @property
    def accepted(self) -> int:
        return self.images.get(ImageStatus.ACCEPTED, 0)

    @property
    def rejected(self) -> int:
        return self.images.get(ImageStatus.REJECTED, 0)

    @property
    def conflict(self) -> int:
        return self.images.get(ImageStatus.CONFLICT, 0)

    @property
    def outcome(self) -> Outcome:
        if self.status is not DownlinkStatus.INGESTED:
            return Outcome.PENDING
        offered = sum(self.images.values()) + sum(self.lidar.values())
        accepted = self.accepted + self.lidar.get(Acceptance.ACCEPTED, 0)
        if offered == 0:
            return Outcome.EMPTY
        if accepted == offered:
            return Outcome.ACCEPTED
        return Outcome.PARTIAL if accepted else Outcome.REJECTED


def downlink_ids(session: Session, *, status: DownlinkStatus | None = None, limit: int | None = None,
                 offset: int = 0) -> tuple[list[int], int]:
    """Ids of downlinks (of `status`), newest first, one page of them; and how many there are."""
    query = select(Downlink.id)
    if status is not None:
        query = query.where(Downlink.status == status)
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    page = query.order_by(Downlink.received_at.desc(), Downlink.id.desc()).offset(offset)
    return list(session.scalars(page if limit is None else page.limit(limit))), total


def downlink_summaries(session: Session, ids: list[int]) -> list[DownlinkSummary]:
    """The summaries of the downlinks `ids`, newest first."""
    if not ids:
        return []

    def per_downlink(column: Any) -> dict[int, int]:
        return {k: n for k, n in session.execute(select(column, func.count())
                                                 .where(column.in_(ids)).group_by(column))}

    kernels = per_downlink(Kernel.downlink_id)
    unused = per_downlink(DownlinkFile.downlink_id)
    images: dict[int | None, dict[ImageStatus, int]] = {}
    for downlink_id, image_status, n in session.execute(
            select(Image.downlink_id, Image.status, func.count())
            .where(Image.downlink_id.in_(ids)).group_by(Image.downlink_id, Image.status)):
        images.setdefault(downlink_id, {})[image_status] = n
    lidar: dict[int | None, dict[Acceptance, int]] = {}
    shots: dict[int | None, tuple[int, int]] = {}
    for downlink_id, lidar_status, n, all_shots, valid_shots in session.execute(
            select(LidarProduct.downlink_id, LidarProduct.status, func.count(), func.sum(LidarProduct.shots),
                   func.sum(LidarProduct.valid_shots))
            .where(LidarProduct.downlink_id.in_(ids)).group_by(LidarProduct.downlink_id, LidarProduct.status)):
        lidar.setdefault(downlink_id, {})[lidar_status] = n
        if lidar_status is Acceptance.ACCEPTED:
            shots[downlink_id] = (int(all_shots or 0), int(valid_shots or 0))
    rows = session.scalars(select(Downlink).where(Downlink.id.in_(ids))
                           .order_by(Downlink.received_at.desc(), Downlink.id.desc()))
    return [DownlinkSummary(id=d.id, name=d.name, path=d.path, received_at=d.received_at,
                            status=d.status, repeat_count=d.repeat_count,
                            last_seen_at=d.last_seen_at, kernels=kernels.get(d.id, 0),
                            images=images.get(d.id, {}), unused_files=unused.get(d.id, 0),
                            model_note=d.model_note, pose_adjustment=d.pose_adjustment,
                            lidar=lidar.get(d.id, {}), lidar_shots=shots.get(d.id, (0, 0))[0],
                            lidar_valid_shots=shots.get(d.id, (0, 0))[1])
            for d in rows]


@dataclass(frozen=True)
class ConfigurationNote:
    """The maplets whose current revision was made with another refinement configuration: how
    many, the digests they were made with (the most common first) and the present one."""

    maplets: int
    digests: tuple[str, ...]
    current: str

    def line(self) -> str:
        made = ", ".join(f"{d[:12]}..." for d in self.digests)
        whose, them = ("maplet's current revision was", "it") if self.maplets == 1 else (
            "maplets' current revisions were", "them")
        return (f"{self.maplets} {whose} made with another configuration (digest {made}, current "
                f"{self.current[:12]}...); `pwm refine-catalog --because-config-changed` refines {them}")


def other_configurations(session: Session, config: RefinementConfig) -> dict[int, str]:
    """The maplets whose current revision was made with a configuration other than `config`
    (by its digest): maplet id -> the digest it was made with. Revisions made before digests
    were recorded are not among them: their configuration is not known."""
    return {m: d for m, d in session.execute(
        select(Maplet.id, MapletRevision.config_digest)
        .join(MapletRevision, MapletRevision.id == Maplet.current_revision_id)
        .where(MapletRevision.config_digest.is_not(None),
               MapletRevision.config_digest != config.digest())) if d is not None}


def configuration_note(session: Session, config: RefinementConfig) -> ConfigurationNote | None:
    """What to tell the operator of the maplets of another configuration than `config`
    (`other_configurations`); None when there are none."""
    other = other_configurations(session, config)
    if not other:
        return None
    return ConfigurationNote(maplets=len(other), current=config.digest(),
                             digests=tuple(d for d, _ in Counter(other.values()).most_common()))
