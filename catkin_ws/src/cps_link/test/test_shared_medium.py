"""Shared medium (Wi-Fi airtime): with topology "shared" both directions together get the one
capacity; the full-duplex veth gives each direction its own. Measured with iperf3 --bidir."""

import pytest
from test_netns_link import needs_link

from cps_harness.testing import link_name
from cps_link import netns_link
from cps_link.netns_link import LinkError, ShapedLink, list_namespaces

pytestmark = needs_link
RATE_MBPS = 20.0


def _bidir(name, topology):
    try:
        with ShapedLink(name, rate=netns_link.tc_rate(RATE_MBPS), topology=topology):
            return netns_link.measure_bidir_mbps(name, seconds=3)
    finally:
        netns_link.link_down(name)
        assert not [ns for ns in list_namespaces() if ns.startswith(f"{name}_")]


@pytest.mark.timeout(90)
def test_both_directions_share_one_capacity_where_the_veth_gives_each_its_own():
    up_shared, down_shared = _bidir(link_name("ksm"), "shared")
    up_duplex, down_duplex = _bidir(link_name("kdx"), "duplex")
    print(
        f"\n{RATE_MBPS:g} Mbit/s, iperf3 --bidir: shared medium {up_shared:.1f} up + {down_shared:.1f} down = "
        f"{up_shared + down_shared:.1f} Mbit/s; full-duplex veth {up_duplex:.1f} + {down_duplex:.1f} = "
        f"{up_duplex + down_duplex:.1f} Mbit/s"
    )
    assert up_shared + down_shared <= 1.05 * RATE_MBPS
    assert up_shared > 0.1 * RATE_MBPS and down_shared > 0.1 * RATE_MBPS
    assert up_duplex + down_duplex >= 1.6 * RATE_MBPS


@pytest.mark.timeout(60)
def test_a_cut_link_carries_nothing_until_it_is_set_again():
    name = link_name("kc")
    try:
        with ShapedLink(name, rate="20mbit", topology="shared") as link:
            netns_link.link_cut(name)
            with pytest.raises(LinkError, match="iperf3 failed"):
                link.measure_mbps(seconds=1)
            netns_link.link_restore(name)
            assert link.measure_mbps(seconds=1) > 10.0
    finally:
        netns_link.link_down(name)
    assert not [ns for ns in list_namespaces() if ns.startswith(f"{name}_")]
