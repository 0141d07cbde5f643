"""Django settings, read from the environment with safe local defaults."""

from __future__ import annotations

import os
import secrets
from pathlib import Path

import dj_database_url
from cryptography.fernet import Fernet

from network.conf import network_settings

from .env import env_bool, env_float, env_int, env_list, env_str, kept_secret

BASE_DIR = Path(__file__).resolve().parent.parent
DATA_DIR = Path(env_str("BRIDGEOS_DATA_DIR", str(BASE_DIR / ".data")))
DATA_DIR.mkdir(parents=True, exist_ok=True)
# Every daphne and Celery process writes its Prometheus values here and any one serves their
# sum on /metrics (monitoring/prometheus.py says why). Set before anything imports prometheus_client;
# `make run` empties it at start so a dead process's counters from an earlier run do not linger.
os.environ.setdefault("PROMETHEUS_MULTIPROC_DIR", str(DATA_DIR / "prometheus"))
Path(os.environ["PROMETHEUS_MULTIPROC_DIR"]).mkdir(parents=True, exist_ok=True)


def _secret_key() -> str:
    """Return SECRET_KEY from the environment, else one generated once and kept in DATA_DIR."""
    configured = env_str("SECRET_KEY")
    if configured:
        return configured
    # A generated key kept on disk survives restarts, so sessions and signed tokens stay valid.
    path = DATA_DIR / "secret_key"
    if not path.exists():
        path.write_text(secrets.token_urlsafe(50))
        path.chmod(0o600)
    return path.read_text().strip()


SECRET_KEY = _secret_key()


def _pki_key() -> str:
    """Return the key sealing the VPN PKI's private keys: BRIDGEOS_PKI_KEY(_FILE), else one kept in DATA_DIR."""
    configured = env_str("BRIDGEOS_PKI_KEY")
    if configured:
        return configured
    return kept_secret(DATA_DIR / "pki_key", Fernet.generate_key)


BRIDGEOS_PKI_KEY = _pki_key()
DEBUG = env_bool("DEBUG", False)
ALLOWED_HOSTS = env_list("ALLOWED_HOSTS", ["127.0.0.1", "localhost", "[::1]"])
CSRF_TRUSTED_ORIGINS = env_list("CSRF_TRUSTED_ORIGINS", [])
# Behind TLS (see the README), set SECURE_COOKIES=1 so session and CSRF cookies never travel in clear.
SESSION_COOKIE_SECURE = CSRF_COOKIE_SECURE = env_bool("SECURE_COOKIES", False)
SECURE_PROXY_SSL_HEADER = ("HTTP_X_FORWARDED_PROTO", "https") if env_bool("BEHIND_TLS_PROXY", False) else None
# Production behind TLS: browsers remember to use HTTPS only (HSTS), and plain HTTP is redirected.
SECURE_HSTS_SECONDS = env_int("SECURE_HSTS_SECONDS", 31_536_000 if SESSION_COOKIE_SECURE else 0)
SECURE_SSL_REDIRECT = env_bool("SECURE_SSL_REDIRECT", False)
SECURE_REFERRER_POLICY = "same-origin"
SESSION_COOKIE_SAMESITE = CSRF_COOKIE_SAMESITE = "Lax"

INSTALLED_APPS = [
    "daphne",
    "django.contrib.admin",
    "django.contrib.auth",
    "django.contrib.contenttypes",
    "django.contrib.sessions",
    "django.contrib.messages",
    "django.contrib.staticfiles",
    "rest_framework",
    "drf_spectacular",
    "drf_spectacular_sidecar",
    "channels",
    "robots.apps.RobotsConfig",
    "skills.apps.SkillsConfig",
    "monitoring.apps.MonitoringConfig",
    "dashboard.apps.DashboardConfig",
    "network.apps.NetworkConfig",
    "recordings.apps.RecordingsConfig",
    "registry.apps.RegistryConfig",
    "teams.apps.TeamsConfig",
    "audit.apps.AuditConfig",
    "rollouts.apps.RolloutsConfig",
    "logs.apps.LogsConfig",
]

MIDDLEWARE = [
    # Outermost, so a request's latency includes every other middleware.
    "monitoring.middleware.RequestLatency",
    "django.middleware.security.SecurityMiddleware",
    "bridgeos_cloud.middleware.CompressLargeResponses",
    "whitenoise.middleware.WhiteNoiseMiddleware",
    "django.contrib.sessions.middleware.SessionMiddleware",
    "django.middleware.common.CommonMiddleware",
    "django.middleware.csrf.CsrfViewMiddleware",
    "django.contrib.auth.middleware.AuthenticationMiddleware",
    "django.contrib.messages.middleware.MessageMiddleware",
    "django.middleware.clickjacking.XFrameOptionsMiddleware",
    "bridgeos_cloud.csp.ContentSecurityPolicy",
    # After authentication and every view: it writes who did what, and how it ended.
    "audit.middleware.AuditTrail",
    # Innermost on purpose: see its docstring.
    "bridgeos_cloud.middleware.SyncChain",
]

ROOT_URLCONF = "bridgeos_cloud.urls"
ASGI_APPLICATION = "bridgeos_cloud.asgi.application"

TEMPLATES = [
    {
        "BACKEND": "django.template.backends.django.DjangoTemplates",
        "DIRS": [BASE_DIR / "templates"],
        "APP_DIRS": True,
        "OPTIONS": {
            "context_processors": [
                "django.template.context_processors.request",
                "django.contrib.auth.context_processors.auth",
                "django.contrib.messages.context_processors.messages",
            ],
        },
    },
]

# PostgreSQL (psycopg 3) in production and tests; a SQLite file is the embedded default.
DATABASES = {
    "default": dj_database_url.parse(
        env_str("DATABASE_URL") or f"sqlite:///{DATA_DIR / 'db.sqlite3'}",
        conn_max_age=env_int("DATABASE_CONN_MAX_AGE", 60),
        conn_health_checks=True,
    )
}
if DATABASES["default"]["ENGINE"] == "django.db.backends.postgresql" and env_bool("DATABASE_POOL", True):
    # Persistent per-thread connections would be held by idle threads (HTTP workers, consumers'
    # database threads). A shared pool reuses them and caps how many PostgreSQL sees (waiting
    # requests queue instead of failing with "too many clients").
    DATABASES["default"]["CONN_MAX_AGE"] = 0
    DATABASES["default"]["CONN_HEALTH_CHECKS"] = False
    DATABASES["default"].setdefault("OPTIONS", {})["pool"] = {
        "min_size": env_int("DATABASE_POOL_MIN", 2),
        "max_size": env_int("DATABASE_POOL_MAX", 20),
        "timeout": env_float("DATABASE_POOL_TIMEOUT", 10.0),
    }
if DATABASES["default"]["ENGINE"] == "django.db.backends.sqlite3":
    # `make run` without PostgreSQL: daphne, two Celery processes and beat write to one file.
    # WAL lets readers run beside the writer, and IMMEDIATE transactions wait for the write lock
    # up front rather than failing at once when a read would have to become a write.
    DATABASES["default"].setdefault("OPTIONS", {}).update(
        {"transaction_mode": "IMMEDIATE", "timeout": 20, "init_command": "PRAGMA journal_mode=WAL;"}
    )
if DATABASES["default"]["ENGINE"] == "django.db.backends.postgresql":
    # JIT compiling costs ~10 ms per query; with estimates off (a bulk load not yet analysed)
    # PostgreSQL spent it on 2 ms lookups. These are short queries: never JIT them.
    DATABASES["default"].setdefault("OPTIONS", {})["options"] = "-c jit=off"
# The password apart from the URL, so a deployment can hand it over as a Docker secret (DATABASE_PASSWORD_FILE).
if env_str("DATABASE_PASSWORD"):
    DATABASES["default"]["PASSWORD"] = env_str("DATABASE_PASSWORD")
DEFAULT_AUTO_FIELD = "django.db.models.BigAutoField"

AUTH_PASSWORD_VALIDATORS = [
    {"NAME": "django.contrib.auth.password_validation.UserAttributeSimilarityValidator"},
    {"NAME": "django.contrib.auth.password_validation.MinimumLengthValidator"},
    {"NAME": "django.contrib.auth.password_validation.CommonPasswordValidator"},
    {"NAME": "django.contrib.auth.password_validation.NumericPasswordValidator"},
]
# Request bodies above 1 MiB are refused (the same ceiling as WebSocket frames).
DATA_UPLOAD_MAX_MEMORY_SIZE = 1_048_576
LOGIN_URL = "login"
LOGIN_REDIRECT_URL = "dashboard:index"
LOGOUT_REDIRECT_URL = "login"

LANGUAGE_CODE = "en-us"
TIME_ZONE = "UTC"
USE_I18N = True
USE_TZ = True

STATIC_URL = "static/"
STATICFILES_DIRS = [BASE_DIR / "static"]
STATIC_ROOT = DATA_DIR / "staticfiles"
# Empty unless collectstatic ran; it exists so whitenoise does not warn about it on every start.
STATIC_ROOT.mkdir(exist_ok=True)
# Serve straight from the app and project folders, so `make run` needs no collectstatic.
WHITENOISE_USE_FINDERS = True
WHITENOISE_AUTOREFRESH = DEBUG

# Redis carries the channel layer and the Celery broker; without it everything stays in-process.
REDIS_URL = env_str("REDIS_URL") or None

if REDIS_URL:
    CHANNEL_LAYERS = {
        "default": {
            "BACKEND": "bridgeos_cloud.channellayer.ChannelLayer",
            "CONFIG": {
                # redis-py's default pool (100 sockets) fails under a large fleet.
                "hosts": [
                    {
                        "address": REDIS_URL,
                        "max_connections": env_int("REDIS_MAX_CONNECTIONS", 1000),
                        # redis-py 8 reads with a 5 s timeout by default, exactly the layer's blocking
                        # pop of 5 s, so idle receives would fail; give the read room above it.
                        "socket_timeout": 30,
                    }
                ],
                # The default capacity (100) overflows and drops messages for busy subscribers.
                "capacity": env_int("CHANNEL_LAYER_CAPACITY", 5000),
                "expiry": 30,
            },
        }
    }
else:
    CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}

CELERY_BROKER_URL = REDIS_URL or "memory://"
CELERY_RESULT_BACKEND = REDIS_URL or "cache+memory://"
CELERY_TASK_ALWAYS_EAGER = env_bool("CELERY_TASK_ALWAYS_EAGER", REDIS_URL is None)
CELERY_TASK_EAGER_PROPAGATES = True
CELERY_TASK_ACKS_LATE = True
CELERY_TASK_REJECT_ON_WORKER_LOST = True
CELERY_WORKER_PREFETCH_MULTIPLIER = 1
CELERY_RESULT_EXPIRES = 3600
# A task of a worker killed mid-task (acked late, so still in Redis) goes back to the queue after this
# long: longer than any task runs (steps retry within seconds), far shorter than kombu's hour, so a
# deployment of a killed worker is finished minutes later, not an hour. Every worker sweeps for such
# tasks every CELERY_UNACKED_RESTORE_S seconds, and once when it starts.
CELERY_BROKER_TRANSPORT_OPTIONS = {
    "visibility_timeout": env_float("CELERY_VISIBILITY_TIMEOUT_S", 300.0),
    "unacked_restore_interval": env_float("CELERY_UNACKED_RESTORE_S", 30.0),
    "unacked_restore_throttle": 1,
}
# Separate queues let several clouds (or test runs) share one Redis database.
CELERY_TASK_DEFAULT_QUEUE = env_str("CELERY_TASK_DEFAULT_QUEUE", "celery")
CELERY_BROKER_CONNECTION_RETRY_ON_STARTUP = True
CELERY_TIMEZONE = TIME_ZONE
# Threads applying robots' reports in each daphne (a robot's own frames stay in order).
BRIDGEOS_ROBOT_DB_THREADS = env_int("BRIDGEOS_ROBOT_DB_THREADS", 4)
# How long a robot may take from its old version's stop to the release running before it fails its gate.
BRIDGEOS_ROLLOUT_INSTALL_TIMEOUT_S = env_float("BRIDGEOS_ROLLOUT_INSTALL_TIMEOUT_S", 120.0)
# How long a reconnected robot's own restart of its Skills (with the stored release) is waited for.
BRIDGEOS_ROLLOUT_CONVERGE_GRACE_S = env_float("BRIDGEOS_ROLLOUT_CONVERGE_GRACE_S", 3.0)
BRIDGEOS_ROLLOUT_FETCH_GRACE_S = env_float("BRIDGEOS_ROLLOUT_FETCH_GRACE_S", 3.0)
CELERY_BEAT_SCHEDULE = {
    "prune-audit": {
        "task": "audit.tasks.prune_audit",
        "schedule": 3600.0,
    },
    "prune-metrics": {
        "task": "monitoring.tasks.prune_metrics",
        "schedule": 3600.0,
    },
    # Metric partitions of the coming days exist before their first point (the default partition is a net).
    "ensure-metric-partitions": {
        "task": "monitoring.tasks.ensure_metric_partitions",
        "schedule": 3600.0,
    },
    # Component logs past BRIDGEOS_LOG_RETENTION_DAYS go (whole day partitions), the coming days' are created.
    "prune-logs": {
        "task": "logs.tasks.prune_logs",
        "schedule": 3600.0,
    },
    # What the cloud copies printed since the last round, stored like robots' lines (location "cloud").
    "collect-cloud-logs": {
        "task": "logs.tasks.collect_cloud_logs",
        "schedule": env_float("BRIDGEOS_CLOUD_LOG_COLLECT_S", 2.0),
        "options": {"expires": env_float("BRIDGEOS_CLOUD_LOG_COLLECT_S", 2.0)},
    },
    # Desired cloud components vs what runs: restart the crashed, remove orphans, collect stats.
    "reconcile-cloud": {
        "task": "skills.tasks.reconcile_cloud",
        "schedule": env_float("BRIDGEOS_CLOUD_RECONCILE_S", 5.0),
        "options": {"expires": env_float("BRIDGEOS_CLOUD_RECONCILE_S", 5.0)},
    },
    # Every active rollout moves a step: installs, gates, batches, rollbacks.
    "advance-rollouts": {
        "task": "rollouts.tasks.advance_rollouts",
        "schedule": env_float("BRIDGEOS_ROLLOUT_TICK_S", 1.0),
        "options": {"expires": env_float("BRIDGEOS_ROLLOUT_TICK_S", 1.0)},
    },
    # Robots of a dead server process go offline even when no live server process is left to sweep.
    "sweep-dead-processes": {
        "task": "robots.tasks.sweep_dead_processes",
        "schedule": env_float("BRIDGEOS_PROCESS_HEARTBEAT_S", 2.0),
        "options": {"expires": env_float("BRIDGEOS_PROCESS_HEARTBEAT_S", 2.0)},
    },
}

REST_FRAMEWORK = {
    "DEFAULT_AUTHENTICATION_CLASSES": [
        "robots.authentication.ApiTokenAuthentication",
        "rest_framework.authentication.SessionAuthentication",
    ],
    "DEFAULT_PERMISSION_CLASSES": ["rest_framework.permissions.IsAuthenticated"],
    "DEFAULT_SCHEMA_CLASS": "drf_spectacular.openapi.AutoSchema",
    "DEFAULT_PAGINATION_CLASS": "rest_framework.pagination.LimitOffsetPagination",
    "PAGE_SIZE": 100,
    "EXCEPTION_HANDLER": "bridgeos_cloud.errors.api_exception_handler",
}
SPECTACULAR_SETTINGS = {
    "TITLE": "bridgeOS Cloud Robot API",
    "DESCRIPTION": "Manage robots, Skills and their components, and query their metrics.",
    "VERSION": "0.1.0",
    "SERVE_INCLUDE_SCHEMA": False,
    # Swagger UI assets ship with the package: the docs work without reaching a CDN.
    "SWAGGER_UI_DIST": "SIDECAR",
    "SWAGGER_UI_FAVICON_HREF": "SIDECAR",
    "REDOC_DIST": "SIDECAR",
    "ENUM_NAME_OVERRIDES": {
        "LocationEnum": "skills.choices.LOCATION_CHOICES",
        "SideEnum": "skills.choices.ACTIVE_LOCATION_CHOICES",
        "SkillStatusEnum": "skills.choices.SKILL_STATUS_CHOICES",
        "ComponentStatusEnum": "skills.choices.COMPONENT_STATUS_CHOICES",
        "RobotStatusEnum": "robots.choices.RobotStatus",
        "LevelEnum": "monitoring.choices.Level",
        "SourceEnum": "monitoring.choices.Source",
    },
}

# bridgeOS knobs.
BRIDGEOS = {
    # Who may scrape /metrics: these addresses (CIDRs), or anyone sending `Authorization: Bearer <token>`.
    "METRICS_ALLOW": env_list("BRIDGEOS_METRICS_ALLOW", ["127.0.0.1/32", "::1/128"]),
    "METRICS_TOKEN": env_str("BRIDGEOS_METRICS_TOKEN", ""),
    "METRIC_RETENTION_DAYS": env_float("BRIDGEOS_METRIC_RETENTION_DAYS", 30.0),
    # Audit entries older than this are deleted (hourly); the chain is anchored at the first one kept.
    "AUDIT_RETENTION_DAYS": env_float("BRIDGEOS_AUDIT_RETENTION_DAYS", 365.0),
    # Daily metric partitions (PostgreSQL) kept created this many days ahead of today.
    "METRIC_PARTITION_AHEAD_DAYS": env_int("BRIDGEOS_METRIC_PARTITION_AHEAD_DAYS", 7),
    # Component log lines older than this are dropped (hourly, whole day partitions on PostgreSQL).
    "LOG_RETENTION_DAYS": env_float("BRIDGEOS_LOG_RETENTION_DAYS", 7.0),
    # Per WebSocket connection: frames per second on average, and the burst allowed above it.
    "ROBOT_FRAMES_PER_S": env_float("BRIDGEOS_ROBOT_FRAMES_PER_S", 200.0),
    "ROBOT_FRAME_BURST": env_float("BRIDGEOS_ROBOT_FRAME_BURST", 1000.0),
    "CLIENT_FRAMES_PER_S": env_float("BRIDGEOS_CLIENT_FRAMES_PER_S", 50.0),
    "CLIENT_FRAME_BURST": env_float("BRIDGEOS_CLIENT_FRAME_BURST", 200.0),
    # How long a robot's old token keeps working after the admin's "rotate" action: connected robots are
    # given the new one at once; one offline all this time is shut out once it ends.
    "TOKEN_ROTATION_GRACE_S": env_float("BRIDGEOS_TOKEN_ROTATION_GRACE_S", 3600.0),
    # Lifetime of an API token from /api/auth; /api/auth/renew extends it by as much.
    "API_TOKEN_TTL_S": env_float("BRIDGEOS_API_TOKEN_TTL_S", 24 * 3600.0),
    # Bridges (/ws/rosbridge/<robot>/, /ws/foxglove/<robot>/): a browser's ticket lives this long and serves once;
    # each client gets at most this many bytes per second (its robot-side queues drop the oldest past it),
    # this many frames queued in the cloud (the oldest dropped past it), and may send frames this large,
    # this often.
    "BRIDGE_TICKET_TTL_S": env_float("BRIDGEOS_BRIDGE_TICKET_TTL_S", 60.0),
    # Enough for a 1 MB point cloud at 10 Hz with room to catch up after a hiccup.
    "BRIDGE_CLIENT_BYTES_PER_S": env_int("BRIDGEOS_BRIDGE_CLIENT_BYTES_PER_S", 16 * 1024 * 1024),
    "BRIDGE_CLIENT_QUEUE": env_int("BRIDGEOS_BRIDGE_CLIENT_QUEUE", 1000),
    "BRIDGE_CLIENT_QUEUE_BYTES": env_int("BRIDGEOS_BRIDGE_CLIENT_QUEUE_BYTES", 32 * 1024 * 1024),
    "BRIDGE_MAX_FRAME_BYTES": env_int("BRIDGEOS_BRIDGE_MAX_FRAME_BYTES", 1024 * 1024),
    "BRIDGE_CLIENT_FRAMES_PER_S": env_float("BRIDGEOS_BRIDGE_CLIENT_FRAMES_PER_S", 500.0),
    "BRIDGE_CLIENT_FRAME_BURST": env_float("BRIDGEOS_BRIDGE_CLIENT_FRAME_BURST", 1000.0),
    # How long a client's command waits for the robot's reply.
    "COMMAND_WAIT_S": env_float("BRIDGEOS_COMMAND_WAIT_S", 5.0),
    # A ROS master the cloud runs for robots that have none (ws://... not; http://HOST:11311).
    "CLOUD_ROS_MASTER": env_str("BRIDGEOS_CLOUD_ROS_MASTER", ""),
    # Threads serving HTTP requests in each server process (each holds a pooled DB connection).
    "HTTP_THREADS": env_int("BRIDGEOS_HTTP_THREADS", 8),
    # Threads serving HTTP writes: a command holds one while it waits on its robot, with no DB connection.
    "HTTP_WRITE_THREADS": env_int("BRIDGEOS_HTTP_WRITE_THREADS", 64),
    # Robot state JSON kept per server process; every read revalidates it against the database.
    "STATE_CACHE_BYTES": env_int("BRIDGEOS_STATE_CACHE_BYTES", 64 * 1024 * 1024),
    # Cloud orchestration (skills.cloud): what runs cloud components and how robots reach them.
    "CLOUD_RUNTIME": env_str("BRIDGEOS_CLOUD_RUNTIME", "process"),
    # Tells this cloud's containers apart from other clouds' on a shared engine (default: from the database).
    "CLOUD_ID": env_str("BRIDGEOS_CLOUD_ID", ""),
    # The address robots reach cloud containers' published ports and host-network services at.
    "CLOUD_HOST": env_str("BRIDGEOS_CLOUD_HOST", "127.0.0.1"),
    # This cloud's own HTTP address as its cloud copies reach it: their BRIDGEOS_MANAGER_URL starts here.
    "CLOUD_URL": env_str("BRIDGEOS_CLOUD_URL", "http://127.0.0.1:8000"),
    # A dedicated ROS master per robot that has none (default: with the swarm and docker runtimes).
    "CLOUD_ROS_MASTERS": env_str("BRIDGEOS_CLOUD_ROS_MASTERS", ""),
    "CLOUD_ROS_MASTER_PORTS": env_str("BRIDGEOS_CLOUD_ROS_MASTER_PORTS", "41311-41999"),
    "CLOUD_ROS_IMAGE": env_str("BRIDGEOS_CLOUD_ROS_IMAGE", "bridgeos/ros:noetic"),
    # A Fast DDS discovery server per ROS 2 robot (its cloud graph): the UDP ports they use, and their image.
    "CLOUD_ROS2_DISCOVERY_PORTS": env_str("BRIDGEOS_CLOUD_ROS2_DISCOVERY_PORTS", "42811-43999"),
    "CLOUD_ROS2_IMAGE": env_str("BRIDGEOS_CLOUD_ROS2_IMAGE", "bridgeos/ros2:jazzy"),
    # ROS nodes in the cloud: "host" networking (peers on this host reach them) or the robot's overlay network.
    "CLOUD_ROS_NETWORK": env_str("BRIDGEOS_CLOUD_ROS_NETWORK", "host"),
    "CLOUD_START_TIMEOUT_S": env_float("BRIDGEOS_CLOUD_START_TIMEOUT_S", 60.0),
    "CLOUD_VOLUMES_DIR": env_str("BRIDGEOS_CLOUD_VOLUMES_DIR", str(DATA_DIR / "cloud" / "volumes")),
    # Robots' MCAP recordings: one folder per recording (its chunks while they arrive, then one .mcap file).
    "RECORDINGS_DIR": env_str("BRIDGEOS_RECORDINGS_DIR", str(DATA_DIR / "recordings")),
    # What one robot's Skill volumes may hold in the cloud, all together; volume sync past it is refused.
    "VOLUME_QUOTA_BYTES": env_int("BRIDGEOS_VOLUME_QUOTA_MB", 1024) * 1024 * 1024,
    # A crashed cloud component is restarted after 1, 2, 4 ... s (at most this), and given up on
    # after CLOUD_MAX_RESTARTS crashes within CLOUD_RESTART_WINDOW_S.
    "CLOUD_RESTART_BACKOFF_MAX_S": env_float("BRIDGEOS_CLOUD_RESTART_BACKOFF_MAX_S", 60.0),
    "CLOUD_MAX_RESTARTS": env_int("BRIDGEOS_CLOUD_MAX_RESTARTS", 5),
    "CLOUD_RESTART_WINDOW_S": env_float("BRIDGEOS_CLOUD_RESTART_WINDOW_S", 300.0),
    # Each server process refreshes its liveness key this often; a process silent for PROCESS_TTL_S
    # is taken for dead and its robots are marked disconnected by the others.
    "PROCESS_HEARTBEAT_S": env_float("BRIDGEOS_PROCESS_HEARTBEAT_S", 2.0),
    "PROCESS_TTL_S": env_float("BRIDGEOS_PROCESS_TTL_S", 10.0),
    # Failed logins (/api/auth, robot tokens) allowed per identity and address, and per address, in a window.
    "AUTH_FAILURES": env_int("BRIDGEOS_AUTH_FAILURES", 10),
    "AUTH_FAILURES_PER_ADDRESS": env_int("BRIDGEOS_AUTH_FAILURES_PER_ADDRESS", 100),
    "AUTH_WINDOW_S": env_float("BRIDGEOS_AUTH_WINDOW_S", 300.0),
    # The cloud as the token server of Distribution registries (registry/): the key signing their
    # tokens (PEM; default: one made once and kept in DATA_DIR as registry_key.pem), the `iss` they
    # expect, the `aud` of a request that names no service, and how long a token is good for.
    "REGISTRY_KEY": env_str("BRIDGEOS_REGISTRY_KEY", ""),
    "REGISTRY_ISSUER": env_str("BRIDGEOS_REGISTRY_ISSUER", "bridgeos-cloud"),
    "REGISTRY_SERVICE": env_str("BRIDGEOS_REGISTRY_SERVICE", "bridgeos-registry"),
    "REGISTRY_TOKEN_TTL_S": env_float("BRIDGEOS_REGISTRY_TOKEN_TTL_S", 300.0),
    # The pull token a cloud copy's Swarm service carries for its nodes (skills/cloud/swarmauth.py): it
    # must outlive a task waiting for a node with room or a slow pull; every restart brings a new one.
    "REGISTRY_SWARM_TOKEN_S": env_float("BRIDGEOS_REGISTRY_SWARM_TOKEN_S", 86400.0),
    # The cloud's own registry as images name it (host[:port]); a Skill's images there are pinned
    # by digest when it is added (registry/pinning.py). Empty: images are kept as written. How the
    # cloud reaches it (default http on loopback, else https) and the CA file its certificate is
    # checked with (default: the system's).
    "REGISTRY_HOST": env_str("BRIDGEOS_REGISTRY_HOST", ""),
    "REGISTRY_URL": env_str("BRIDGEOS_REGISTRY_URL", ""),
    "REGISTRY_CA": env_str("BRIDGEOS_REGISTRY_CA", ""),
}

# Robots' subnets (IPAM pools), the VPN and TLS: see network/conf.py and the README.
BRIDGEOS_NETWORK = network_settings()

LOGGING = {
    "version": 1,
    "disable_existing_loggers": False,
    "formatters": {"plain": {"format": "%(asctime)s %(levelname)s %(name)s: %(message)s"}},
    "filters": {
        "robot_state_as_warning": {"()": "bridgeos_cloud.logfilters.RobotStateAsWarning"},
        "client_fault_as_warning": {"()": "bridgeos_cloud.logfilters.ClientFaultAsWarning"},
    },
    "handlers": {
        "console": {"class": "logging.StreamHandler", "formatter": "plain", "filters": ["client_fault_as_warning"]}
    },
    "loggers": {"django.request": {"filters": ["robot_state_as_warning"]}},
    "root": {"handlers": ["console"], "level": env_str("LOG_LEVEL", "INFO")},
}
