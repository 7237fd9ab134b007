"""Equipment left out of or moved in the hall, for change-detection runs (no rospy)."""
import dataclasses
from typing import Sequence


@dataclasses.dataclass(frozen=True)
class SiteMove:
    """Shift equipment item `name` by (dx_m, dy_m) in map."""

    name: str
    dx_m: float
    dy_m: float

    @classmethod
    def parse(cls, text):
        """From `name:dx_m:dy_m`; ValueError says what is wrong."""
        parts = text.split(":")
        if len(parts) != 3:
            raise ValueError(f"'{text}' is not name:dx_m:dy_m")
        return cls(parts[0], float(parts[1]), float(parts[2]))


def apply_site_changes(site, without: Sequence[str] = (), moves: Sequence[SiteMove] = ()):
    """The site without the named items and with the moves applied; KeyError names the known items."""
    for name in without:
        site = site.without(name)
    for move in moves:
        site = site.moved(move.name, move.dx_m, move.dy_m)
    return site
