"""What a viewer will show of a recording: its default blueprint and the loops' drawn points,
read back from the .rrd file (rerun's chunk reader, no viewer needed).

Used by the tests and by `scripts/viewer_screenshot.py` to check the layout a user gets.
"""

from __future__ import annotations

import dataclasses
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.offline.rrd_scan import open_rrd

# rerun's ContainerKind values as stored in the blueprint
CONTAINER_KINDS = {1: "tabs", 2: "horizontal", 3: "vertical", 4: "grid"}


@dataclasses.dataclass
class ViewNode:
    """A view or a container of the blueprint."""

    kind: str  # a container kind ("tabs", ...) or the view class ("TimeSeries", ...)
    name: str | None
    origin: str | None = None  # views only
    children: list[ViewNode] = dataclasses.field(default_factory=list)
    properties: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    def views(self) -> list[ViewNode]:
        """Every view below this node, depth first."""
        if not self.children and self.origin is not None:
            return [self]
        return [v for c in self.children for v in c.views()]


def _rows(path: Path, blueprint: bool) -> dict[str, dict[str, Any]]:
    """entity path -> {component: latest value} of the file's first blueprint or recording."""
    reader = open_rrd(path)
    store = None
    if blueprint:
        stores = reader.blueprints()
        if not stores:
            raise ValueError(f"{path}: the recording has no blueprint")
        store = stores[0]
    out: dict[str, dict[str, Any]] = {}
    for chunk in reader.stream(store=store):
        for row in chunk.to_record_batch().to_pylist():
            out.setdefault(chunk.entity_path, {}).update(
                {k: v for k, v in row.items() if ":" in k and v is not None}
            )
    return out


def read_blueprint(path: str | Path) -> ViewNode:
    """The default blueprint stored in `path`, as a tree from the viewport's root container."""
    path = Path(path)
    rows = _rows(path, blueprint=True)
    root_bytes = rows["/viewport"]["ViewportBlueprint:root_container"][0]
    return _node(rows, f"/container/{uuid.UUID(bytes=bytes(root_bytes))}")


def _node(rows: dict[str, dict[str, Any]], entity: str) -> ViewNode:
    row = rows[entity]
    props = {e[len(entity) + 1 :]: r for e, r in rows.items() if e.startswith(entity + "/")}
    name = (
        row.get("ViewBlueprint:display_name")
        or row.get("ContainerBlueprint:display_name")
        or [None]
    )[0]
    if entity.startswith("/container/"):
        kind = CONTAINER_KINDS.get(row["ContainerBlueprint:container_kind"][0], "?")
        children = [_node(rows, "/" + c) for c in row.get("ContainerBlueprint:contents", [])]
        return ViewNode(kind, name, children=children, properties=props)
    return ViewNode(
        row["ViewBlueprint:class_identifier"][0],
        name,
        origin=row["ViewBlueprint:space_origin"][0],
        properties=props,
    )


def read_strips(path: str | Path, entity: str) -> list[np.ndarray]:
    """Every LineStrips2D strip logged at `entity` (each an N x 2 array), in file order."""
    reader = open_rrd(path)
    strips = []
    for chunk in reader.stream():
        if chunk.entity_path != "/" + entity.strip("/"):
            continue
        for row in chunk.to_record_batch().to_pylist():
            for strip in row.get("LineStrips2D:strips") or []:
                strips.append(np.asarray(strip, dtype=float).reshape(-1, 2))
    return strips
