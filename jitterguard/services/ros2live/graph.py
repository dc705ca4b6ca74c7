"""The ROS 2 adapters' place in rmw_zenoh's ROS graph: their liveliness tokens, declared on the ROS side's session
for as long as the service runs (Zenoh withdraws them when it stops or its session is lost, and the ROS graph
forgets the node)."""

from __future__ import annotations

from collections.abc import Sequence

import zenoh

from ...runtime import Service
from .ros_keys import RosEndpoint, RosNaming, ros_node


class RosGraphService(Service):
    """A service with a ROS 2 side: ``ros2-in`` and ``ros2-out``."""

    def declare_graph(self, ros: zenoh.Session, naming: RosNaming, endpoints: Sequence[RosEndpoint]) -> list[str]:
        """Declare this service's node and ``endpoints`` in the ROS graph (rmw_zenoh only; none behind a bridge),
        undeclared with the service; returns the tokens, node first."""
        namespace, node = ros_node(self.name, self.ns)
        tokens = naming.graph_tokens(str(ros.zid()), node, namespace, endpoints)
        for token in tokens:
            self._declared.append(ros.liveliness().declare_token(token))
        if tokens:
            self.log.info("in the ROS graph as node %s/%s (ROS domain %d)", namespace, node, naming.domain_id)
        return tokens
