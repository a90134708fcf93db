"""Reading the YAML and JSON that users write (mission files, sweep files, a run's config).

:func:`load_text` reads either, with the same rules for both: a key given twice in one
mapping is refused (PyYAML and ``json`` keep the last one silently, so a second ``pois:``
would drop the first list), a document nested too deeply for Python's recursion is refused,
and YAML numbers with an exponent but no dot (``3e-4``) are numbers, as in YAML 1.2 and
JSON (YAML 1.1 reads them as strings). Every mistake is a :class:`~roverswarm.errors.UserError`
that starts with ``where`` (e.g. ``mission file 'm.yaml'``), on one line.

This module imports nothing of the package but :mod:`roverswarm.errors`, so the environment
(:mod:`roverswarm.env.missions`) may use it.
"""

from __future__ import annotations

import contextlib
import json
import re
from typing import Any

import yaml

from roverswarm.errors import UserError

EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
"""Numbers YAML 1.1 leaves as strings: an exponent without a dot (``3e-4``) or without a sign
(``1.0e5``)."""


class UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping and reads ``3e-4`` as a
    number."""

    def construct_mapping(self, node, deep=False):
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            with contextlib.suppress(TypeError):  # unhashable keys are left to the caller's checks
                if key in seen:
                    raise UserError(f"line {key_node.start_mark.line + 1}: '{key}' is given twice")
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


UniqueKeyLoader.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT_FLOAT, list("-+0123456789."))


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object from its ``pairs``, refusing a key given twice."""
    keys = [key for key, _ in pairs]
    twice = sorted({key for key in keys if keys.count(key) > 1})
    if twice:
        raise UserError(f"'{twice[0]}' is given twice in one object")
    return dict(pairs)


def load_text(text: str, kind: str, where: str, aliases: bool = True) -> Any:
    """The document in ``text``, ``kind`` ``"JSON"`` or ``"YAML"`` (see the module docstring);
    with ``aliases=False`` a YAML alias is refused before anything is built, so a small file
    cannot expand into a huge document. Mistakes raise :class:`UserError` naming ``where``."""
    try:
        if kind == "JSON":
            return json.loads(text, object_pairs_hook=_unique_pairs)
        if not aliases:
            for event in yaml.parse(text, Loader=UniqueKeyLoader):
                if isinstance(event, yaml.AliasEvent):
                    raise UserError(f"YAML aliases (*{event.anchor}) are not allowed")
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a safe loader)
    except (json.JSONDecodeError, yaml.YAMLError) as error:
        flat = " ".join(str(error).split())  # one line, whatever the parser's layout
        raise UserError(f"{where} is not valid {kind}: {flat}") from None
    except RecursionError:
        raise UserError(f"{where} is nested too deeply to read") from None
    except UserError as error:
        raise UserError(f"{where}: {error}") from None
    except ValueError as error:  # e.g. an integer of more digits than Python converts (4300)
        raise UserError(f"{where} is not valid {kind}: {str(error).split(';')[0]}") from None
