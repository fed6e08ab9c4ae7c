"""``wiggly schema``: print the JSON Schema of scene files."""

from __future__ import annotations

import argparse
import json

HELP = "print the JSON Schema of scene files"
DESCRIPTION = """\
Print the JSON Schema (draft 2020-12) of wiggly scene files, for editors and
validators (e.g. VS Code's Even Better TOML, taplo, check-jsonschema). The same
schema ships in the package as wiggly/data/scene.schema.json. It checks the
structure (keys, types, ranges); `wiggly animate` additionally checks references
(keyframe groups, times in range) and the groups against the mesh."""
EPILOG = """\
examples:
  wiggly schema > scene.schema.json
  check-jsonschema --schemafile scene.schema.json shot.toml"""


def add_args(parser: argparse.ArgumentParser) -> None:
    """``wiggly schema`` has no options."""


def run(args: argparse.Namespace) -> int:
    from wiggly.scene import scene_schema

    print(json.dumps(scene_schema(), indent=2))
    return 0
