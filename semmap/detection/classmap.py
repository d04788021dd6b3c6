"""Translation of a model's classes into our semantic classes.

A detector trained on COCO knows ``chair``, ``couch`` and ``dining table``; our map knows
``chair``, ``sofa`` and ``desk``. The config's class map says which model class (by name or by
index written as a string) becomes which of ours; model classes it does not name are ignored.
An empty map keeps the model classes whose names already are ours (a model trained on our
classes needs no map).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from semmap.errors import PerceptionError


def parse_names_metadata(text: str) -> list[str]:
    """Class names from an Ultralytics ``names`` metadata string (``"{0: 'person', ...}"``).

    Raises :class:`PerceptionError` if the text is not a dict of index -> name or a list.
    """
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError) as exc:
        raise PerceptionError(f"model metadata 'names' is not a dict or list literal: {text[:80]!r}") from exc
    if isinstance(value, dict):
        try:
            items = sorted((int(k), str(v)) for k, v in value.items())
        except (TypeError, ValueError) as exc:
            raise PerceptionError("model metadata 'names' keys must be class indices") from exc
        if [k for k, _ in items] != list(range(len(items))):
            raise PerceptionError("model metadata 'names' indices are not 0..C-1")
        return [v for _, v in items]
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    raise PerceptionError(f"model metadata 'names' has type {type(value).__name__}; expected dict or list")


class ClassMap:
    """Model class index -> semantic class index (into ``semantic_names``), or -1 if ignored."""

    def __init__(
        self,
        model_names: Sequence[str],
        semantic_names: Sequence[str],
        class_map: Mapping[str, str | Sequence[str]] | None = None,
    ) -> None:
        """Resolve ``class_map`` (model name or index string -> semantic name, or a list of
        semantic names the model cannot tell apart: the first is reported).

        Raises :class:`PerceptionError` if a key names no model class, a value is not one of
        ``semantic_names``, or no model class maps to anything (the detector would be mute).
        """
        self.model_names = list(model_names)
        self.semantic_names = list(semantic_names)
        sem_index = {n: i for i, n in enumerate(self.semantic_names)}
        lookup = np.full(len(self.model_names), -1, dtype=np.int64)
        if class_map:
            by_name = {n: i for i, n in enumerate(self.model_names)}
            for key, value in class_map.items():
                targets = [value] if isinstance(value, str) else list(value)
                bad = [t for t in targets if t not in sem_index]
                if bad or not targets:
                    raise PerceptionError(
                        f"detector.class_map[{key!r}] = {value!r}: {bad or 'nothing'} is not a semantic "
                        f"class (classes: {self.semantic_names})"
                    )
                target = targets[0]
                if key in by_name:
                    idx = by_name[key]
                elif key.isdigit() and int(key) < len(self.model_names):
                    idx = int(key)
                else:
                    shown = ", ".join(repr(n) for n in self.model_names[:12])
                    more = " ..." if len(self.model_names) > 12 else ""
                    raise PerceptionError(
                        f"detector.class_map key {key!r} is neither a model class name nor an "
                        f"index < {len(self.model_names)} (model classes: {shown}{more})"
                    )
                lookup[idx] = sem_index[target]
        else:
            for i, n in enumerate(self.model_names):
                if n in sem_index:
                    lookup[i] = sem_index[n]
        if not (lookup >= 0).any():
            raise PerceptionError(
                f"no model class maps to a semantic class (model classes: "
                f"{self.model_names[:12]}{' ...' if len(self.model_names) > 12 else ''}; "
                f"semantic classes: {self.semantic_names}); set detector.class_map"
            )
        #: (C,) semantic index per model class, -1 = ignored.
        self.lookup: NDArray[np.int64] = lookup

    @property
    def wanted_mask(self) -> NDArray[np.bool_]:
        """(C,) True for model classes that map to a semantic class."""
        return self.lookup >= 0

    def semantic_ids(self, model_class_ids: NDArray[np.int64]) -> NDArray[np.int64]:
        """(K,) model class indices -> (K,) semantic indices (-1 for ignored classes)."""
        return self.lookup[model_class_ids]
