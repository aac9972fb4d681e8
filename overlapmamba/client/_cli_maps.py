"""``overlapmamba-client maps``: create, list and delete maps (a command group of
:mod:`overlapmamba.client.cli`)."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.table import Table

from overlapmamba.client._cli_options import DEFAULT_URL, KeyOpt, UrlOpt, client, errors, out

maps_app = typer.Typer(help="Create, list and delete maps.", no_args_is_help=True)


@maps_app.command("list")
@errors
def maps_list(url: UrlOpt = DEFAULT_URL, api_key: KeyOpt = None) -> None:
    """List the maps and their sizes."""
    with client(url, api_key) as pr:
        maps = pr.list_maps()
    table = Table("map", "keyframes", "index", "model")
    for m in maps:
        table.add_row(m.map_id, str(m.keyframes), m.index.get("active", ""), m.model_id)
    out.print(table)


@maps_app.command("create")
@errors
def maps_create(
    map_id: Annotated[str, typer.Argument(help="\\[a-z0-9]\\[a-z0-9_-]{0,63}")],
    index: Annotated[str | None, typer.Option(help="flat, ivf or auto")] = None,
    geometry: Annotated[
        bool | None,
        typer.Option(
            "--geometry/--no-geometry",
            help="keyframes keep their geometry for verified answers \\[default: yes]",
        ),
    ] = None,
    sensor: Annotated[
        str | None,
        typer.Option(help="the sensor of scans that name none \\[default: the model's own]"),
    ] = None,
    mount: Annotated[
        str | None,
        typer.Option(
            metavar="HEIGHT[,PITCH[,ROLL]]",
            help="where that sensor sits on scans that name no mount (m, degrees)",
        ),
    ] = None,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """Create a map (idempotent)."""
    with client(url, api_key) as pr:
        m = pr.create_map(map_id, index=index, keep_geometry=geometry, sensor=sensor, mount=mount)
    where = (
        ""
        if m.mount is None
        else f", mounted {m.mount['height']:g} m, pitch {m.mount['pitch_deg']:g}°, "
        f"roll {m.mount['roll_deg']:g}°"
    )
    out.print(
        f"map {m.map_id}: {'created' if m.created else 'exists'}, {m.keyframes} keyframes, "
        f"geometry {'kept' if m.keep_geometry else 'not kept'}, sensor "
        f"{m.sensor or 'the model’s own'}{where}"
    )


@maps_app.command("delete")
@errors
def maps_delete(
    map_id: str,
    yes: Annotated[bool, typer.Option("--yes", help="do not ask")] = False,
    url: UrlOpt = DEFAULT_URL,
    api_key: KeyOpt = None,
) -> None:
    """Delete a map and all its keyframes."""
    if not yes:
        typer.confirm(f"delete map {map_id!r} and all its keyframes?", abort=True)
    with client(url, api_key) as pr:
        pr.delete_map(map_id)
    out.print(f"map {map_id}: deleted")
