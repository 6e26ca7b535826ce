"""An rclpy node on its own context and domain, spun in a background thread.

For programs that talk to the node from outside while doing other work: the benchmarks and
the integration tests."""
from __future__ import annotations

import os
import threading


class BackgroundNode:
    def __init__(self, name: str, domain_id: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from .transport import use_large_data_profile

        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        use_large_data_profile()
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)

    def start(self) -> None:
        """Start spinning; call once the subscriptions are made."""
        self._thread.start()

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:
                if not self.context.ok():
                    return  # shut down while spinning
                raise

    def close(self) -> None:
        import rclpy

        rclpy.try_shutdown(context=self.context)
        if self._thread.is_alive():
            self._thread.join(5)
        self.executor.shutdown()
        self.node.destroy_node()
