"""`medc-train --arch` names the built-in architectures in its help by hand (the command line
stays free of torch until a run starts), so the list is checked against ``nets.ARCHITECTURES``."""
from __future__ import annotations

import re

from medc_training.cli.train import build_parser
from medc_training.nets import ARCHITECTURES


def test_arch_help_names_every_built_in_architecture() -> None:
    action = next(a for a in build_parser()._actions if "--arch" in a.option_strings)
    listed = re.search(r"\(([^)]*)\)", action.help).group(1).split(", ")
    assert sorted(listed) == sorted(ARCHITECTURES)
