"""Loading nodelets into a running manager from one process, as `nodelet load` does for one.

`rosrun nodelet nodelet load TYPE MANAGER __name:=N __ns:=NS ~input:=A _leaf_size:=0.1` (nodelet's
nodelet.cpp, `NodeletInterface::loadNodelet`) sets its private parameters under its own name
/NS/N, then calls MANAGER/load_nodelet (nodelet/NodeletLoad) with name /NS/N, the type, its
remappings resolved as the node resolves them (`~input` -> /NS/N/input) as source and target
lists, its leftover argv and a bond id; the manager's Loader gives the nodelet those remappings
and parameters. `NodeletLoader` makes the same calls for many nodelets without a bond (one
client process, not one per nodelet), unloads them (MANAGER/unload_nodelet) when asked, and
reloads them if the manager restarts.
"""

import dataclasses
import time
from typing import Dict, List, Tuple

import rospy
from nodelet.srv import NodeletList, NodeletLoad, NodeletUnload
from rosgraph.names import ns_join

# How long a load waits for the manager's services before failing (a manager starting pcl_ros's
# plugins on a busy machine takes a few seconds).
MANAGER_WAIT_S = 60.0


_WHY = "an unknown type, a plugin that did not load or a name already taken; the manager's log says which"


class NodeletLoadError(RuntimeError):
    pass


@dataclasses.dataclass(frozen=True)
class NodeletRequest:
    """One nodelet: its name (/ns/name), type, remappings {source: target} and private parameters."""

    name: str
    type: str
    remappings: Dict[str, str]
    params: Dict[str, object]
    argv: Tuple[str, ...] = ()

    def resolved_remappings(self) -> Tuple[List[str], List[str]]:
        """(sources, targets) as nodelet.cpp sends them: private sources under the nodelet's name,
        relative ones in its namespace, targets resolved the same way."""

        def resolve(topic):
            if topic.startswith("~"):
                return ns_join(self.name, topic[1:])
            if topic.startswith("/"):
                return topic
            return ns_join(self.name.rsplit("/", 1)[0] or "/", topic)

        pairs = [(resolve(s), resolve(t)) for s, t in self.remappings.items()]
        return [s for s, _ in pairs], [t for _, t in pairs]


class NodeletLoader:
    """Loads `requests` into the manager `manager` (e.g. /tissue_nodelet_manager) and unloads them."""

    def __init__(self, manager, requests: List[NodeletRequest]):
        self.manager = manager if manager.startswith("/") else "/" + manager
        self.requests = list(requests)
        names = [r.name for r in self.requests]
        if len(set(names)) != len(names):
            raise NodeletLoadError(f"nodelet names repeat: {', '.join(sorted(n for n in names if names.count(n) > 1))}")
        self._load = rospy.ServiceProxy(ns_join(self.manager, "load_nodelet"), NodeletLoad)
        self._unload = rospy.ServiceProxy(ns_join(self.manager, "unload_nodelet"), NodeletUnload)
        self._list = rospy.ServiceProxy(ns_join(self.manager, "list"), NodeletList)
        self.loaded: List[str] = []

    def wait_for_manager(self, timeout_s=MANAGER_WAIT_S):
        try:
            self._load.wait_for_service(timeout=timeout_s)
        except rospy.ROSException as exc:
            raise NodeletLoadError(
                f"nodelet manager {self.manager} did not offer {self._load.resolved_name} "
                f"within {timeout_s:.0f} s (is it running?)"
            ) from exc

    def running(self):
        """The names the manager has loaded; None when it does not answer."""
        try:
            return list(self._list().nodelets)
        except (rospy.ServiceException, rospy.ROSException, OSError):
            return None

    def load_all(self):
        """Loads every request (one already loaded under the same name, e.g. by a loader that died,
        is unloaded first); NodeletLoadError names the first that fails, after unloading the rest."""
        self.wait_for_manager()
        present = set(self.running() or ())
        for request in self.requests:
            if request.name in present:
                self._unload_one(request.name)
            try:
                self.load(request)
            except NodeletLoadError:
                self.unload_all()
                raise

    def load(self, request: NodeletRequest):
        for key, value in request.params.items():
            rospy.set_param(ns_join(request.name, key), value)
        sources, targets = request.resolved_remappings()
        try:
            response = self._load(
                name=request.name,
                type=request.type,
                remap_source_args=sources,
                remap_target_args=targets,
                my_argv=list(request.argv),
                bond_id="",
            )
        except (rospy.ServiceException, rospy.ROSException, OSError) as exc:
            # The manager answers a failed load (unknown type, plugin not loadable, name taken) with
            # an error, not success=false.
            raise NodeletLoadError(
                f"{self.manager} failed to load {request.type} as {request.name} ({exc}): {_WHY}"
            ) from exc
        if not response.success:
            raise NodeletLoadError(f"{self.manager} failed to load {request.type} as {request.name}: {_WHY}")
        self.loaded.append(request.name)
        rospy.loginfo(
            f"{rospy.get_name()}: loaded {request.type} as {request.name} into {self.manager} "
            f"({', '.join(f'{s} -> {t}' for s, t in zip(sources, targets))})"
        )

    def _unload_one(self, name):
        try:
            return self._unload(name=name).success
        except (rospy.ServiceException, rospy.ROSException, OSError):
            return False

    def unload_all(self):
        """Unloads what this loader loaded (the manager may already be gone: then nothing is left)."""
        for name in reversed(self.loaded):
            self._unload_one(name)
        self.loaded = []

    def watch(self, period_s=2.0, should_stop=rospy.is_shutdown):
        """Until `should_stop()`: if the manager restarts (our nodelets missing), loads them again."""
        while not should_stop():
            time.sleep(period_s)
            running = self.running()
            if running is None or should_stop():
                continue
            missing = [r for r in self.requests if r.name not in running]
            if missing:
                rospy.logwarn(
                    f"{rospy.get_name()}: {self.manager} lost {', '.join(r.name for r in missing)} "
                    "(restarted?): loading them again"
                )
                self.loaded = [n for n in self.loaded if n in running]
                for request in missing:
                    self.load(request)


def voxel_grid_requests(fleet, robots=None) -> List[NodeletRequest]:
    """pcl/VoxelGrid for each robot with the names, topics and parameters `nodelet load` gets
    from cps_transport.voxel_grid_command (the per-robot layout), starting at the cloud level
    nearest the robot's voxel_leaf_m."""
    from cps_transport.cloud_levels import initial_leaf_m
    from cps_transport.voxel_grid_command import (
        VOXEL_NODELET_TYPE,
        voxel_nodelet_name,
        voxel_nodelet_params,
        voxel_nodelet_remaps,
    )

    out = []
    for name in robots or fleet.robot_names:
        robot = fleet.robot(name)
        out.append(
            NodeletRequest(
                name=voxel_nodelet_name(robot),
                type=VOXEL_NODELET_TYPE,
                remappings=voxel_nodelet_remaps(robot),
                params=voxel_nodelet_params(robot, initial_leaf_m(fleet, robot)),
            )
        )
    return out
