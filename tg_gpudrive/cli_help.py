"""The help format of every `tg-gpudrive` command (tg_gpudrive.cli's one parser). Standard library only."""

from __future__ import annotations

import argparse


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; an option's help ends with "(default: VALUE)" unless it already says
    its default, the option is required, or the default is None or empty (its help says what happens
    then); a switch's default is "off"."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text.lower() or action.required or action.default is argparse.SUPPRESS:
            return text
        if action.nargs == 0 and action.default is False:  # a switch
            return f"{text} (default: off)"
        if action.default is None or action.default == [] or not (action.option_strings or action.nargs in ("?", "*")):
            return text
        return f"{text} (default: %(default)s)"
