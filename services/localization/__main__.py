"""``python -m services.localization``: the map server + AMCL service."""

from services.common.service import service_main
from services.localization.config import LocalizationConfig
from services.localization.node import run

if __name__ == "__main__":
    service_main("localization", {"localization": LocalizationConfig}, run)
