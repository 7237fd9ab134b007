"""The shaped link: namespaces, tbf on both directions, iperf3, live rate change, cleanup always,
and the clear refusal without root. Skipped (only) where root or network namespaces are missing."""

import os
import shutil
import subprocess
import sys

import pytest

from cps_harness.testing import link_name
from cps_link import netns_link
from cps_link.netns_link import LinkError, ShapedLink, list_namespaces

pytestmark = pytest.mark.waiting

NODE = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_link")


def _capable():
    try:
        netns_link.check_capability()
        return None
    except LinkError as exc:
        return str(exc)


needs_link = pytest.mark.skipif(_capable() is not None, reason=f"{_capable()}")


def _ours(name):
    return [ns for ns in list_namespaces() if ns.startswith(f"{name}_")]


@needs_link
@pytest.mark.slow
def test_link_is_shaped_both_ways_changes_live_and_is_removed():
    name = link_name("tl")
    try:
        with ShapedLink(name, rate="60mbit") as link:
            assert sorted(_ours(name)) == [f"{name}_phys", f"{name}_twin"]
            forward = link.measure_mbps(seconds=2)
            backward = link.measure_mbps(seconds=2, reverse=True)
            print(f"\niperf3 over the 60mbit link: {forward:.1f} Mbit/s phys->twin, {backward:.1f} twin->phys")
            # TCP goodput under a 60 Mbit/s token bucket (IP/TCP headers take ~5 %).
            assert 40.0 < forward <= 61.0 and 40.0 < backward <= 61.0
            link.set_rate("20mbit")
            slow = link.measure_mbps(seconds=2)
            print(f"after `set --rate 20mbit`: {slow:.1f} Mbit/s")
            assert 12.0 < slow <= 21.0
            # Nothing of ours is visible outside the namespaces.
            assert f"{name}_p" not in subprocess.run(["ip", "link"], capture_output=True, text=True).stdout
        assert _ours(name) == []
    finally:
        netns_link.link_down(name)


@needs_link
def test_link_is_removed_when_the_block_fails():
    name = link_name("tf")
    with pytest.raises(RuntimeError, match="boom"):
        with ShapedLink(name):
            assert _ours(name)
            raise RuntimeError("boom")
    assert _ours(name) == []
    netns_link.link_down(name)  # idempotent


@needs_link
def test_delay_and_loss_use_netem_or_say_why_not():
    name = link_name("td")
    try:
        netns_link.link_up(name, delay_ms=20.0, loss_pct=0.0)
    except LinkError as exc:
        assert "netem" in str(exc)
        assert _ours(name) == []
        return
    try:
        show = subprocess.run(
            ["ip", "netns", "exec", f"{name}_phys", "tc", "qdisc", "show"], capture_output=True, text=True
        ).stdout
        assert "netem" in show and "delay 20ms" in show and "tbf" in show
    finally:
        netns_link.link_down(name)
    assert _ours(name) == []


@pytest.mark.parametrize("mbps, rate", [(60.0, "60mbit"), (57.5, "57500kbit"), (0.5, "500kbit"), (1000, "1000mbit")])
def test_tc_rate_says_the_same_rate_as_the_mbit_per_s(mbps, rate):
    assert netns_link.tc_rate(mbps) == rate
    assert netns_link.rate_bits_per_s(rate) == pytest.approx(mbps * 1e6)


def test_the_default_rate_is_the_fleet_files_link_rate():
    from cps_fleet.fleet import load_fleet

    assert netns_link.rate_bits_per_s(netns_link.fleet_rate()) == pytest.approx(load_fleet().link.available_mbps * 1e6)
    assert ShapedLink("cpstdef").rate == netns_link.fleet_rate()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(name="Bad Name"), "link name"),
        (dict(rate="fast"), "not a tc rate"),
        (dict(rate="0mbit"), "must be > 0"),
        (dict(delay_ms=-1.0), "delay"),
        (dict(loss_pct=100.0), "loss"),
    ],
)
def test_bad_link_arguments_are_refused_before_anything_is_created(kwargs, match):
    with pytest.raises(LinkError, match=match):
        netns_link.link_up(**kwargs)


@needs_link
@pytest.mark.slow
def test_cli_up_measure_set_down():
    name = link_name("tc")

    def cli(*args):
        return subprocess.run([sys.executable, NODE, *args], capture_output=True, text=True, timeout=60)

    try:
        assert cli("up", "--name", name, "--rate", "30mbit").returncode == 0
        again = cli("up", "--name", name)
        assert again.returncode == 2 and "already exists" in again.stderr
        measured = cli("measure", "--name", name, "--seconds", "1")
        assert measured.returncode == 0 and "Mbit/s" in measured.stdout
        assert 15.0 < float(measured.stdout.split()[0]) <= 31.0
        assert cli("set", "--name", name, "--rate", "10mbit").returncode == 0
        env = cli(
            "exec", "phys", "--name", name, "--master-port", "11999", "--", "sh", "-c", "echo $ROS_IP $ROS_MASTER_URI"
        )
        assert env.stdout.split() == ["10.201.0.1", "http://10.201.0.2:11999"]
    finally:
        assert cli("down", "--name", name).returncode == 0
        assert cli("down", "--name", name).returncode == 0
    assert _ours(name) == []


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root to drop to nobody")
def test_without_root_the_cli_says_so_and_offers_loopback():
    out = subprocess.run(
        [
            "setpriv",
            "--reuid=65534",
            "--regid=65534",
            "--clear-groups",
            sys.executable,
            NODE,
            "up",
            "--name",
            "cpstnoroot",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 2
    assert "needs root" in out.stderr and "--link none" in out.stderr
