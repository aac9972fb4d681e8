"""What the ``overlapmamba-client`` commands share: their options (``--url``, ``--api-key``,
``--map``, ``--mount``, the ROS recordings' topics…), the consoles they print to, how they
turn an error into a message and an exit code (1: the service refused; 2: it could not be
reached, or bad arguments), and the client they talk through."""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum
from functools import wraps
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from overlapmamba.client._base import Timeouts, check_mount
from overlapmamba.client._exceptions import APIError, ClientError
from overlapmamba.client._sync import PlaceRecognitionClient

console = Console(stderr=True, soft_wrap=True)
out = Console()
F = TypeVar("F", bound=Callable[..., Any])

UrlOpt = Annotated[
    str, typer.Option("--url", envvar="OVERLAPMAMBA_URL", help="the service's base URL")
]
KeyOpt = Annotated[
    str | None, typer.Option("--api-key", envvar="OVERLAPMAMBA_API_KEY", help="API key")
]
MapOpt = Annotated[str, typer.Option("--map", "-m", help="map id")]


class GraphReader(StrEnum):
    """The back end a ``--g2o`` file is written for (``posegraph.READERS``)."""

    g2o = "g2o"
    gtsam = "gtsam"


GraphReaderOpt = Annotated[
    GraphReader,
    typer.Option(
        help="with --g2o: the back end that reads the file, whose reading of the rotation's "
        "information it is written for (GTSAM's readG2o, 4.2 or later, takes it over the "
        "rotation vector, g2o over half of it)"
    ),
]
VerifyOpt = Annotated[
    bool,
    typer.Option(
        "--verify/--no-verify",
        help="the server registers the top candidates against their keyframes' geometry",
    ),
]
TopicOpt = Annotated[
    str | None,
    typer.Option(help="ROS recordings: the PointCloud2 topic (when it holds several)"),
]
OdometryOpt = Annotated[
    str | None,
    typer.Option(help="ROS recordings: a nav_msgs/Odometry topic giving each scan's pose"),
]
TfOpt = Annotated[
    str | None,
    typer.Option(
        "--tf",
        help="ROS recordings: poses from /tf and /tf_static in this fixed frame (FIXED, or "
        "FIXED:CHILD when the LiDAR's frame is not the scans' header frame)",
    ),
]
SensorOpt = Annotated[
    str | None,
    typer.Option(
        help="the sensor the scans come from (`overlapmamba sensors`, GET /v1/sensors): "
        "vlp16, os1-64, …; default: the drive's manifest's, else the map's"
    ),
]


def check_mount_option(value: str | None) -> str | None:
    try:
        return check_mount(value)
    except ValueError as err:
        raise typer.BadParameter(
            f"{err} (HEIGHT[,PITCH[,ROLL]]: height above the "
            "ground in (0, 10] m, pitch and roll within ±45°)"
        ) from None


MountOpt = Annotated[
    str | None,
    typer.Option(
        callback=check_mount_option,
        help="where the sensor sits: HEIGHT[,PITCH[,ROLL]] (m above the ground; degrees, pitch "
        "positive looking down ahead, roll positive left side up), e.g. 0.7 for a delivery "
        "robot; the service levels the scans and moves them to the model's mount",
    ),
]
DRIVE_HELP = (
    "sequence folder (KITTI layout, PCD folder) or ROS recording (.bag, a folder of a split "
    "recording's .bag files, rosbag2, .mcap)"
)
DEFAULT_URL = "http://127.0.0.1:8000"


def errors(func: F) -> F:
    @wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except APIError as err:
            console.print(f"[bold red]error:[/] {err.status} {err.code}: {escape(err.message)}")
            raise typer.Exit(1) from None
        except ClientError as err:
            console.print(f"[bold red]error:[/] {escape(str(err))}")
            raise typer.Exit(2) from None
        except (ValueError, OSError) as err:
            console.print(f"[bold red]error:[/] {escape(str(err))}")
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def make_map(pr: PlaceRecognitionClient, map_id: str, sensor: str | None) -> None:
    """The drive's map, made (or found) once the service is known to take the drive's
    sensor: one it does not know was refused at the first scan, after an empty map had been
    made for it."""
    if sensor is not None:
        names = [s.get("name") for s in pr.sensors().get("sensors", [])]
        if sensor not in names:
            raise ValueError(
                f"the service knows no sensor {sensor!r}; allowed: {', '.join(map(str, names))}"
                " (a sensor file under [sensors] files adds one)"
            )
    pr.create_map(map_id)


def within(path: Path, folder: Path) -> bool:
    """``path`` is ``folder`` or lies inside it (both resolved: links, ``..``)."""
    p, f = path.resolve(), folder.resolve()
    return p == f or f in p.parents


def client(url: str, api_key: str | None, mount: str | None = None) -> PlaceRecognitionClient:
    return PlaceRecognitionClient(url, api_key=api_key, timeout=Timeouts(read=120), mount=mount)
