"""ROS namespaces for the tools around the node (``mireg play``, ``mireg listen``).

The node's topics are relative, so ``--ros-args -r __ns:=/left`` moves all of them under
/left (one node per camera). A tool created in the same namespace, using the same relative
names, meets that node; in the root namespace the names are the absolute ones.
"""
from __future__ import annotations

from ..errors import InputError


def add_namespace_argument(parser, what: str) -> None:
    parser.add_argument("--namespace", default="/", metavar="NS",
                        help=f"{what} (the node's __ns, e.g. /left; default: the root namespace)")


def checked_namespace(text: str) -> str:
    """'/left', 'left' or 'left/' -> '/left'; '' or '/' -> '/'. A name ROS refuses is an InputError."""
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    namespace = "/" + text.strip().strip("/")
    try:
        validate_namespace(namespace)
    except InvalidNamespaceException as exc:
        raise InputError(f"--namespace {text!r} is not a valid ROS namespace: "
                         f"{str(exc).splitlines()[0].rstrip(':')}") from None
    return namespace


def relative(topic: str) -> str:
    """'/camera/camera/color/image_raw' -> 'camera/camera/color/image_raw' (then resolved in the namespace)."""
    return topic.lstrip("/")
