"""`vmocap bench images`: one person per scene (images.py) or the subject among others
(`--people N`, people.py), which builds on images.py's scoring."""

from __future__ import annotations

import argparse

from . import images, people

add_arguments = images.add_arguments


def run(args: argparse.Namespace) -> int:
    if args.people != 1:
        files, _, rig = images.prepare(args)
        return people.run(args, rig)
    return images.run(args)
