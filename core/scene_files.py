"""A scene file as a host receives it: ``environment.gltf`` / ``environment.usda`` and the files
it references (``GET /api/v1/environment.gltf?bundle=1`` and ``lightprobe export``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["EnvironmentFiles"]


@dataclass
class EnvironmentFiles:
    """A scene file (``environment.gltf`` / ``environment.usda``) and the files it references,
    ``{relative path: bytes}``; :meth:`save` writes them into a folder, keeping the layout."""

    name: str
    document: bytes
    files: dict[str, bytes]

    def save(self, folder: Any) -> Any:
        from pathlib import Path

        from lightprobe.core.fsutil import atomic_write

        root = Path(folder)
        for rel, data in self.files.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(root / rel, data)
        root.mkdir(parents=True, exist_ok=True)
        atomic_write(root / self.name, self.document)
        return root / self.name
