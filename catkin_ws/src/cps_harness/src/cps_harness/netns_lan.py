"""Several hosts on one shared segment (e.g. the robots, the twin and a rogue laptop on one Wi-Fi):
a network namespace per host, each joined by a veth pair to a Linux bridge in a switch namespace,
optionally shaped with tbf on the host ends. Needs root; `SharedLan` always removes everything."""

import contextlib
import os

from cps_link.netns_link import (
    ClosingContext,
    LinkError,
    _check_name,
    _run,
    check_capability,
    list_namespaces,
    rate_bits_per_s,
)

SUBNET_PREFIX = 24


class SharedLan(ClosingContext):
    """`with SharedLan("cpszr", {"phys": "10.203.0.1", "twin": "10.203.0.2", "rogue": "10.203.0.3"}) as lan:`
    namespaces `<name>_<host>` and `<name>_sw`; `lan.argv(host, [...])` runs a command on a host."""

    def __init__(self, name, hosts, rate=None):
        _check_name(name)
        if not hosts or any(len(f"{name}{h}") > 15 for h in hosts):
            raise LinkError(f"host names of LAN '{name}' must be short (interface names are at most 15 characters)")
        if rate:
            rate_bits_per_s(rate)
        self.name, self.hosts, self.rate = name, dict(hosts), rate

    def namespace(self, host):
        return f"{self.name}_{host}"

    @property
    def namespaces(self):
        return [self.namespace(h) for h in (*self.hosts, "sw")]

    def argv(self, host, argv, env=None):
        assignments = [f"{k}={v}" for k, v in (env or {}).items()]
        return ["ip", "netns", "exec", self.namespace(host), "env", *assignments, *argv]

    def __enter__(self):
        check_capability()
        present = [ns for ns in self.namespaces if ns in list_namespaces()]
        if present:
            raise LinkError(f"namespaces {present} already exist (another run?)")
        return self._set_up_or_close(self._create)

    def _create(self):
        sw = self.namespace("sw")
        _run(["ip", "netns", "add", sw])
        _run(["ip", "-n", sw, "link", "add", "br0", "type", "bridge"])
        _run(["ip", "-n", sw, "link", "set", "br0", "up"])
        for host, address in self.hosts.items():
            ns = self.namespace(host)
            _run(["ip", "netns", "add", ns])
            _run(
                [
                    "ip",
                    "-n",
                    sw,
                    "link",
                    "add",
                    f"{self.name}{host}",
                    "type",
                    "veth",
                    "peer",
                    "name",
                    "eth0",
                    "netns",
                    ns,
                ]
            )
            _run(["ip", "-n", sw, "link", "set", f"{self.name}{host}", "master", "br0", "up"])
            _run(["ip", "-n", ns, "addr", "add", f"{address}/{SUBNET_PREFIX}", "dev", "eth0"])
            _run(["ip", "-n", ns, "link", "set", "lo", "up"])
            _run(["ip", "-n", ns, "link", "set", "eth0", "up"])
            if self.rate:
                _run(
                    [
                        "ip",
                        "netns",
                        "exec",
                        ns,
                        "tc",
                        "qdisc",
                        "add",
                        "dev",
                        "eth0",
                        "root",
                        "tbf",
                        "rate",
                        self.rate,
                        "burst",
                        "131072",
                        "latency",
                        "50ms",
                    ]
                )

    def close(self):
        present = list_namespaces()
        for ns in self.namespaces:
            if ns in present:
                for pid in _run(["ip", "netns", "pids", ns], check=False).stdout.split():
                    with contextlib.suppress(ProcessLookupError, ValueError):
                        os.kill(int(pid), 9)
                _run(["ip", "netns", "del", ns], check=False)
        left = [ns for ns in self.namespaces if ns in list_namespaces()]
        if left:
            raise LinkError(f"could not remove namespaces {left}")
