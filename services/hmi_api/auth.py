"""The HMI's login (``services.common.auth``, shared with the site's fleet view) under its historical name.

``python -m services.hmi_api.auth hash`` prints a hash for ``hmi_api.password_hash``.
"""

from __future__ import annotations

from services.common.auth import (
    FIRST_RUN_FILE,
    SCRYPT_N,
    SCRYPT_P,
    SCRYPT_R,
    LoginThrottle,
    TokenStore,
    check_hash_format,
    first_run_hash,
    hash_password,
    main,
    new_password,
    verify_password,
)

__all__ = ["FIRST_RUN_FILE", "SCRYPT_N", "SCRYPT_P", "SCRYPT_R", "LoginThrottle", "TokenStore", "check_hash_format",
           "first_run_hash", "hash_password", "main", "new_password", "verify_password"]

if __name__ == "__main__":
    raise SystemExit(main(prog="python -m services.hmi_api.auth"))
