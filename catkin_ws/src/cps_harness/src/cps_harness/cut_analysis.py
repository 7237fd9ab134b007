"""What a link cut did, from link_watch files (tests and the benchmark; ROS-free): when each side
saw the link go and come back, and how old the live data was that arrived after it came back."""

import collections
import dataclasses
from typing import Dict, List, Optional, Tuple

import numpy as np

from cps_fleet import names

LINK_STATE = names.absolute(names.LINK_STATE)


@dataclasses.dataclass
class Watch:
    link: List[Tuple[float, bool, int]]  # receive time, up, outages
    messages: Dict[str, List[Tuple[float, float, int]]]  # topic -> receive, stamp, bytes


def read_watch(path) -> Watch:
    """A link_watch file; a torn last line is skipped."""
    link, messages = [], collections.defaultdict(list)
    with open(path) as stream:
        for line in stream:
            parts = line.split()
            if len(parts) != 4:
                continue
            if parts[0] == LINK_STATE:
                link.append((float(parts[1]), parts[2] == "up", int(parts[3])))
            else:
                messages[parts[0]].append((float(parts[1]), float(parts[2]), int(parts[3])))
    return Watch(link, dict(messages))


def first_state_after(watch: Watch, t_s, up) -> Optional[float]:
    """Receive time of the first link state `up` at or after t_s, else None."""
    return next((t for t, state, _ in watch.link if t >= t_s and state == up), None)


def ages_after(watch: Watch, t_s, topics) -> np.ndarray:
    """Receive - stamp (s) of every message of `topics` received after t_s."""
    return np.array(
        [recv - stamp for topic in topics for recv, stamp, _ in watch.messages.get(topic, []) if recv >= t_s]
    )


def captured_before(watch: Watch, t_s, topics) -> np.ndarray:
    """t_s - stamp (s) of every message of `topics` received after t_s: how long before t_s it was
    captured (negative: captured after it). A message that waited through a cut shows the wait."""
    return np.array(
        [t_s - stamp for topic in topics for recv, stamp, _ in watch.messages.get(topic, []) if recv >= t_s]
    )


def count_after(watch: Watch, t_s, topic) -> int:
    return sum(1 for recv, _, _ in watch.messages.get(topic, []) if recv >= t_s)


def describe_ages(ages) -> str:
    if len(ages) == 0:
        return "no messages"
    return f"max {np.max(ages):.2f} s, p95 {np.percentile(ages, 95):.2f} s over {len(ages)} messages"
