"""``python -m services.localization``: the map server + AMCL service and its SLAM mapping mode.

The service is ``mapping.ModeSwitcher``: it owns the subscriptions and queries and dispatches them to AMCL
(``node.LocalizationNode``) in navigation mode or to SLAM (``mapping.MappingNode``) in mapping mode.
"""

from services.common.service import ServiceSpec
from services.localization.config import LocalizationConfig
from services.localization.mapping import run

SERVICE = ServiceSpec("localization", {"localization": LocalizationConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
