"""The service's configuration: one typed tree, validated before anything starts.

Sources, highest priority first: explicit overrides (the CLI's options), environment
variables ``OVERLAPMAMBA_*`` (nested fields with ``__``: ``OVERLAPMAMBA_BATCHING__MAX_BATCH=4``),
an optional TOML file (``--config`` or ``OVERLAPMAMBA_CONFIG``), then these defaults.
``overlapmamba dump-config`` prints the merged result as TOML-ready JSON.

The projection is deliberately absent: it comes from the model's own metadata and the scan's
sensor (overlapmamba.service.sensors). The calibrated thresholds (rerank, loop_closure, verify:
overlapmamba.service.calibrated_settings) come from the model file when it carries them; a value
set here overrides it (overlapmamba.service.calibration).
"""

from __future__ import annotations

import difflib
import ipaddress
import os
import re
import tomllib
from collections.abc import Iterable, Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
    TomlConfigSettingsSource,
)

from overlapmamba.core.renamed import RENAMED
from overlapmamba.service.calibrated_settings import (
    CovarianceSettings,
    LoopClosureSettings,
    RerankSettings,
    Section,
    VerifySettings,
)

Role = Literal["robot", "mapper", "viewer", "admin"]
IndexKind = Literal["auto", "flat", "ivf"]
MAP_ID_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"
ORIGIN = re.compile(r"https?://[^/\s?#@]+", re.IGNORECASE)  # a web page's origin, no path


# load_settings(config=...)'s file while it builds a Settings (else OVERLAPMAMBA_CONFIG's)
_CONFIG_FILE: ContextVar[Path | None] = ContextVar("overlapmamba_config_file", default=None)


class LimitSettings(Section):
    max_body_bytes: int = Field(64 << 20, gt=0, description="largest request body, as sent")
    max_decoded_bytes: int = Field(
        128 << 20, gt=0, description="largest body after Content-Encoding (bomb guard)"
    )
    min_points: int = Field(100, ge=1, description="fewer points than this is not a scan")
    max_points: int = Field(2_000_000, ge=1)
    max_batch_scans: int = Field(64, ge=1, description="scans per descriptors:batch request")
    max_batch_keyframes: int = Field(10_000, ge=1, description="rows per keyframes:batch")
    max_k: int = Field(100, ge=1, description="largest k a query may ask for")
    request_timeout_s: float = Field(30.0, gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> LimitSettings:
        if self.min_points > self.max_points:
            raise ValueError("limits.min_points exceeds limits.max_points")
        return self


class BatchSettings(Section):
    max_batch: int = Field(
        2,
        ge=1,
        le=256,
        description="scans per encoder call; each lane holds its batch's working memory "
        "(docs/deploy.md, threads)",
    )
    max_wait_ms: float = Field(
        2.0,
        ge=0,
        description="how long a batch waits to fill while other scans are still being decoded",
    )
    queue_size: int = Field(64, ge=1, description="scans waiting to encode; beyond: 503")
    lanes: int = Field(
        0,
        ge=0,
        le=64,
        description="encoder calls running at once, each on its own thread (0: one a core; "
        "overlapmamba.service.batcher)",
    )
    intra_op_threads: int = Field(
        0, ge=0, description="onnxruntime threads a call (0: the cores shared among the lanes)"
    )


class IndexSettings(Section):
    backend: Literal["faiss", "qdrant"] = Field(
        "faiss", description="faiss: embedded, in data_dir; qdrant: a Qdrant server (qdrant.*)"
    )
    kind: IndexKind = Field("auto", description="default index for new maps")
    approximate_above: int = Field(
        100_000, ge=1, description="'auto' maps switch from exact to IVF above this size"
    )
    ivf_nprobe: int = Field(
        24, ge=1, description="IVF lists searched per query (recall@10 0.99 at 1M, measured)"
    )
    snapshot_every: int = Field(5_000, ge=1, description="writes between automatic snapshots")
    threads: int = Field(
        1,
        ge=1,
        le=256,
        description="FAISS (OpenMP) threads for the whole process. 1: one query's exact "
        "search over 10k keyframes is a fraction of a millisecond on one thread, and more "
        "threads spin against the encoder's on a small machine (docs/deploy.md, sizing)",
    )
    row_cache_mb: int = Field(
        64,
        ge=0,
        le=65_536,
        description="memory for the keyframes searched last, with their yaw features' "
        "spectra (≈ 115 kB a keyframe at 16 × 900 features), shared by every map: a robot's "
        "next query re-ranks mostly the same candidates without reading or transforming them "
        "again. 0: keep none",
    )


class QdrantSettings(Section):
    """The ``qdrant`` backend: each map is the collection ``<collection_prefix><map_id>``."""

    url: str | None = Field(
        None, pattern=r"^https?://", description="the Qdrant server, e.g. http://qdrant:6333"
    )
    api_key: SecretStr | None = Field(None, description="Qdrant's API key (env or file, please)")
    path: Path | None = Field(
        None, description="Qdrant's embedded local mode in this folder (tests, trials; no HNSW)"
    )
    collection_prefix: str = Field(
        "overlapmamba-",
        pattern=r"^[A-Za-z0-9_-]{0,64}$",
        description="collections of this service; two services sharing a Qdrant use two "
        "prefixes (each map records its id, so overlapping prefixes do not mix maps)",
    )
    timeout_s: float = Field(10.0, gt=0, description="per Qdrant call")
    shards: int = Field(1, ge=1, description="new collections: shard_number")
    replication_factor: int = Field(1, ge=1, description="new collections: copies of each shard")
    write_consistency_factor: int = Field(
        1, ge=1, description="new collections: copies that must confirm a write"
    )
    hnsw_ef: int = Field(128, ge=1, description="approximate maps: HNSW candidates per query")

    @model_validator(mode="after")
    def _one_place(self) -> QdrantSettings:
        if self.url is not None and self.path is not None:
            raise ValueError("qdrant: give url or path, not both")
        if self.write_consistency_factor > self.replication_factor:
            raise ValueError("qdrant.write_consistency_factor exceeds qdrant.replication_factor")
        return self


class ObserveSettings(Section):
    insert_min_distance_m: float = Field(
        2.0, ge=0, description="insert=auto: distance moved since the robot's last keyframe"
    )
    insert_min_interval_s: float = Field(
        10.0, ge=0, description="insert=auto: or time elapsed since the robot's last keyframe"
    )
    exclude_recent_s: float = Field(
        30.0, ge=0, description="observe: skip the session's own keyframes this recent"
    )
    stream_queue: int = Field(
        4, ge=1, description="WebSocket frames buffered per connection; beyond: close 1013"
    )


class SensorSettings(Section):
    files: list[Path] = Field(
        default_factory=list,
        description="the operator's own sensors (overlapmamba.core.sensors.catalogue: a .toml or "
        ".json per sensor, or base = a catalogue name and the fields that differ), accepted "
        "by name beside the catalogue's",
    )


class ApiKey(Section):
    name: str = Field(min_length=1)
    role: Role
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="hex SHA-256 of the key")
    maps: list[str] | None = Field(None, description="robot keys: maps it may insert into")
    query_maps: list[str] | None = Field(
        None,
        description="robot keys: maps it may query, observe and stream against, beside those "
        "in maps (unset: any map)",
    )

    @model_validator(mode="after")
    def _maps_for_robots(self) -> ApiKey:
        """``maps`` and ``query_maps`` limit a robot; on another role they would limit
        nothing, which an operator who wrote them did not mean."""
        for field, value in (("maps", self.maps), ("query_maps", self.query_maps)):
            if value is not None and self.role != "robot":
                raise ValueError(
                    f"key {self.name!r}: {field} applies to robot keys only, and this key's "
                    f"role is {self.role!r}; allowed: {field} on a robot key, or none"
                )
            bad = [m for m in value or () if not re.fullmatch(MAP_ID_PATTERN, m)]
            if bad:  # it could never match a map: the key would be refused there, unsaid
                raise ValueError(
                    f"key {self.name!r}: {field} names {bad}, which no map id can be; allowed: "
                    f"map ids, {MAP_ID_PATTERN}"
                )
        if self.query_maps is not None and self.maps is None:
            raise ValueError(
                f"key {self.name!r}: query_maps limits the maps a robot queries besides those "
                "in maps, and without maps it may insert into (and so query) any; allowed: "
                "query_maps with maps"
            )
        return self


class AuthSettings(Section):
    keys: list[ApiKey] = Field(default_factory=list)
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="without keys: web pages (scheme://host[:port]) whose browser writes and "
        "streams are taken besides the service's own pages under a loopback name or an IP "
        "address (overlapmamba.service.origins; others: 403 cross_origin); e.g. the public "
        "origin of a proxy in front. Programs send no Origin and always pass",
    )

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, origins: list[str]) -> list[str]:
        bad = [o for o in origins if not ORIGIN.fullmatch(o.strip().rstrip("/"))]
        if bad:
            raise ValueError(
                f"auth.allowed_origins: {bad[0]!r} is no origin; allowed: scheme://host[:port] "
                "with scheme http or https, no path (e.g. https://ops.example)"
            )
        return origins

    @field_validator("keys")
    @classmethod
    def _unique(cls, keys: list[ApiKey]) -> list[ApiKey]:
        names = [k.name for k in keys]
        if len(set(names)) != len(names):
            raise ValueError("auth.keys: names must be unique")
        seen: dict[str, str] = {}
        for k in keys:  # one key, two entries: which role it gets would be the list's order
            if k.sha256 in seen:
                raise ValueError(
                    f"auth.keys: {seen[k.sha256]!r} and {k.name!r} have the same sha256 (one "
                    "key under two names and roles); allowed: each key once"
                )
            seen[k.sha256] = k.name
        return keys


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="OVERLAPMAMBA_",
        env_nested_delimiter="__",
        extra="forbid",
        protected_namespaces=(),
    )

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Path("data")
    model: Path = Path("models/overlapmamba-hdl64.onnx")
    scan_kernel: bool | Literal["auto"] = Field(
        "auto",
        description="run each selective scan with the C kernel (overlapmamba.core.scan_kernel), "
        "checked against the model's portable graph at load; auto: and only if it is not "
        "slower than the portable graph on this machine (timed at load); false, or a failed "
        "check: onnxruntime runs the portable graph alone",
    )
    insecure: bool = Field(False, description="allow a non-loopback host without API keys")
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    shutdown_delay_s: float = Field(
        0.0,
        ge=0,
        le=300,
        description="after SIGTERM, keep serving this long with /readyz 503 before draining, "
        "so a load balancer stops sending first (≥ its probe interval × failures)",
    )
    log_format: Literal["json", "text"] = Field(
        "json", description="json: one object per line with request ids; text: for a terminal"
    )
    limits: LimitSettings = Field(default_factory=LimitSettings)  # type: ignore[arg-type]
    batching: BatchSettings = Field(default_factory=BatchSettings)  # type: ignore[arg-type]
    index: IndexSettings = Field(default_factory=IndexSettings)  # type: ignore[arg-type]
    observe: ObserveSettings = Field(default_factory=ObserveSettings)  # type: ignore[arg-type]
    loop_closure: LoopClosureSettings = Field(default_factory=LoopClosureSettings)  # type: ignore[arg-type]
    verify: VerifySettings = Field(default_factory=VerifySettings)  # type: ignore[arg-type]
    rerank: RerankSettings = Field(default_factory=RerankSettings)  # type: ignore[arg-type]
    covariance: CovarianceSettings = Field(default_factory=CovarianceSettings)  # type: ignore[arg-type]
    auth: AuthSettings = Field(default_factory=AuthSettings)
    qdrant: QdrantSettings = Field(default_factory=QdrantSettings)  # type: ignore[arg-type]
    sensors: SensorSettings = Field(default_factory=SensorSettings)

    @model_validator(mode="after")
    def _backend_configured(self) -> Settings:
        if self.index.backend == "qdrant" and self.qdrant.url is None and self.qdrant.path is None:
            raise ValueError("index.backend = 'qdrant' needs qdrant.url (or qdrant.path)")
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources = [init_settings, env_settings]
        config = _CONFIG_FILE.get() or os.environ.get("OVERLAPMAMBA_CONFIG")
        if config:
            _check_toml(Path(config))
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=Path(config)))
        return tuple(sources)

    @property
    def loopback(self) -> bool:
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    def check_binding(self) -> None:
        """Without API keys the service answers anyone who can reach it: loopback only,
        unless ``insecure`` says otherwise."""
        if not self.auth.keys and not self.loopback and not self.insecure:
            raise ValueError(
                f"refusing to listen on {self.host} without API keys: configure auth.keys "
                "(see `overlapmamba hash-key`), bind to 127.0.0.1, or pass --insecure"
            )


def _check_toml(path: Path) -> None:
    """The settings file exists and is TOML, else a ValueError naming it (a missing file
    would otherwise read as empty: the service on its defaults, without the file's keys)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ValueError(
            f"config file {path} (--config or OVERLAPMAMBA_CONFIG) cannot be read: "
            f"{err.strerror or err}"
        ) from None
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"config file {path} is not valid TOML: {err}") from None


# OVERLAPMAMBA_ variables that are not settings: the config file, caches and build
# options, the client's, and the test suite's
NOT_SETTINGS = frozenset(
    {
        "CONFIG", "CACHE", "KERNEL_MARCH", "NO_REEXEC", "URL", "API_KEY", "SHARED_DATA",
        "E2E", "E2E_MODEL", "E2E_DRIVE", "IMAGE_TEST",
    }
)  # fmt: skip


def setting_variables() -> set[str]:
    """Every OVERLAPMAMBA_ variable a setting reads (a section's fields, old names too)."""
    names = set()
    for name, field in Settings.model_fields.items():
        names.add(f"OVERLAPMAMBA_{name.upper()}")
        kind = field.annotation
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            fields = {*kind.model_fields, *RENAMED.get(name, {})}
            names.update(f"OVERLAPMAMBA_{name.upper()}__{f.upper()}" for f in fields)
    return names


def unknown_variables(environ: Mapping[str, str]) -> list[tuple[str, str | None]]:
    """The OVERLAPMAMBA_ variables in ``environ`` that nothing reads (a misspelt one is
    otherwise ignored without a word), each with the setting it is nearest, if any."""
    known = setting_variables()
    allowed = known | {f"OVERLAPMAMBA_{n}" for n in NOT_SETTINGS}
    out = []
    for var in sorted(environ):
        upper = var.upper()
        if upper.startswith("OVERLAPMAMBA_") and upper not in allowed:
            near = difflib.get_close_matches(upper, sorted(known), n=1, cutoff=0.75)
            out.append((var, near[0] if near else None))
    return out


def shadowed(
    config: Path | None, environ: Mapping[str, str], given: Iterable[str] = ()
) -> list[tuple[str, str]]:
    """The OVERLAPMAMBA_ variables in ``environ`` that override a setting the config file
    (``config``, else OVERLAPMAMBA_CONFIG's) sets, each with that setting's name: the
    environment wins, so a container image's ENV hid a mounted file's ``data_dir``, unsaid.
    ``given``: the settings the command line sets (dotted), which win over both: left out."""
    named = config or environ.get("OVERLAPMAMBA_CONFIG")
    try:
        table = tomllib.loads(Path(named).read_text()) if named else {}
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return []  # load_settings says what is wrong with the file
    keys = set(table)
    keys.update(f"{k}.{f}" for k, v in table.items() if isinstance(v, dict) for f in v)
    keys -= set(given)
    out = []
    for var in sorted(environ):
        upper = var.upper()
        key = upper.removeprefix("OVERLAPMAMBA_").lower().replace("__", ".")
        if upper.startswith("OVERLAPMAMBA_") and upper != "OVERLAPMAMBA_CONFIG" and key in keys:
            out.append((var, key))
    return out


def load_settings(config: Path | None = None, **overrides: Any) -> Settings:
    """Settings from a TOML file (if given), the environment and explicit overrides."""
    values = {k: v for k, v in overrides.items() if v is not None}
    if config is not None and not config.is_file():
        what = "is a folder" if config.is_dir() else "does not exist"
        raise ValueError(f"config file {config} {what}; allowed: a TOML file")
    # the file reaches settings_customise_sources through a context variable: the process
    # environment is never written (another thread's Settings() would read it)
    token = _CONFIG_FILE.set(config)
    try:
        return Settings(**values)
    except SettingsError as err:  # says "field 'sensors'", not which variable nor what it takes
        field = str(err).split('"')[1] if '"' in str(err) else ""
        prefix = f"OVERLAPMAMBA_{field.upper()}"
        named = sorted(k for k in os.environ if field and k.startswith(prefix))
        raise ValueError(
            f"{', '.join(named) or 'an OVERLAPMAMBA_ variable'} cannot be read: a list or a "
            "table in a variable is JSON, e.g. OVERLAPMAMBA_SENSORS__FILES='[\"a.toml\"]' "
            f"({err})"
        ) from None
    finally:
        _CONFIG_FILE.reset(token)
