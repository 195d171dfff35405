"""beehave's Fast DDS profile: participants without the XTypes TypeLookup service.

Fast DDS 3.2 (ROS 2 Kilted's) reads its pending type requests in the TypeLookup reply thread
without a lock while discovery adds to them (``TypeLookupManager::notify_callbacks``); a
robot process discovering endpoints of types it does not use itself died of SIGSEGV there in
our stress runs (the native stack from its core file). With the participant property
``fastdds.type_propagation`` set to ``disabled`` Fast DDS makes no TypeLookup service and
announces no type information, and endpoints match by type name, as ROS 2 expects.

Fast DDS reads its profile from the file ``FASTDDS_DEFAULT_PROFILES_FILE`` names (or the
deprecated ``FASTRTPS_DEFAULT_PROFILES_FILE``), then ``DEFAULT_FASTDDS_PROFILES.xml`` in the
working directory unless ``SKIP_DEFAULT_XML_FILE=1``, once per process, when it makes the
first participant. This module needs no rclpy (the test suite and tools import it early).
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from collections.abc import MutableMapping
from pathlib import Path

log = logging.getLogger(__name__)

#: The profile a RosContext gives its process when the user names none (packaged).
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")
FASTDDS_PROFILE_ENV = "FASTDDS_DEFAULT_PROFILES_FILE"
#: Still read by the ROS 2 middleware (deprecated): a file it names is the user's profile.
LEGACY_PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
WORKDIR_PROFILE = "DEFAULT_FASTDDS_PROFILES.xml"
TYPE_PROPAGATION = "fastdds.type_propagation"
#: The values that keep the TypeLookup service off (Fast DDS's TypePropagation).
SAFE_PROPAGATION = ("disabled", "registration_only")
_NS = {"d": "http://www.eprosima.com"}
_checked: set[str] = set()


def use_fastdds_profile(environ: MutableMapping[str, str] | None = None) -> Path:
    """Give this process (and its children) beehave's profile unless the user has one;
    returns the profile Fast DDS will read. Call it before the first participant exists.

    A profile of the user's own (either variable, or ``DEFAULT_FASTDDS_PROFILES.xml`` in the
    working directory) is kept, and a warning, once per file, says when its default
    participant profile leaves type propagation on."""
    env = os.environ if environ is None else environ
    own = env.get(FASTDDS_PROFILE_ENV) or env.get(LEGACY_PROFILE_ENV)
    if own:
        _check_users_profile(Path(own))
        return Path(own)
    workdir = Path.cwd() / WORKDIR_PROFILE
    if env.get("SKIP_DEFAULT_XML_FILE") != "1" and workdir.is_file():
        _check_users_profile(workdir)  # loaded after ours: its default participant wins
    if not FASTDDS_PROFILE.is_file():
        log.warning("beehave's Fast DDS profile %s is missing (a broken installation): "
                    "participants run with Fast DDS's TypeLookup service, which can crash a "
                    "process under load (docs/ros.md)", FASTDDS_PROFILE)
    env[FASTDDS_PROFILE_ENV] = str(FASTDDS_PROFILE)
    return FASTDDS_PROFILE


def type_propagation(profile: Path) -> str | None:
    """The ``fastdds.type_propagation`` value of ``profile``'s default participant profile
    (None: not set, which Fast DDS takes as ``enabled``). Raises OSError or ET.ParseError."""
    root = ET.parse(profile).getroot()
    for participant in root.iterfind(".//d:participant", _NS):
        if participant.get("is_default_profile") != "true":
            continue
        for prop in participant.iterfind(".//d:property", _NS):
            if (prop.findtext("d:name", namespaces=_NS) or "").strip() == TYPE_PROPAGATION:
                return (prop.findtext("d:value", namespaces=_NS) or "").strip()
    return None


def _check_users_profile(profile: Path) -> None:
    key = str(profile)
    if key in _checked:
        return
    _checked.add(key)
    try:
        value = type_propagation(profile)
    except (OSError, ET.ParseError) as err:
        log.warning("the Fast DDS profile %s cannot be read (%s); Fast DDS reports it too",
                    profile, err)
        return
    if value not in SAFE_PROPAGATION:
        log.warning("the Fast DDS profile %s leaves %s %s in its default participant "
                    "profile: Fast DDS 3.2's TypeLookup service can crash a process under "
                    "load (docs/ros.md). Add <property><name>%s</name><value>disabled"
                    "</value></property> to it, as %s does", profile, TYPE_PROPAGATION,
                    "unset" if value is None else f"= {value!r}", TYPE_PROPAGATION,
                    FASTDDS_PROFILE)
