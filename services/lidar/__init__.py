"""Lidar service: SICK LMS111 over CoLa A/TCP -> ``scan``.

``cola`` (framing, tokens, commands), ``telegrams`` (LMDscandata, LMPscancfg, STlms decoders) and ``convert``
(REP-103 LaserScan) are the pure core; ``link`` and ``node`` are the asyncio shell; ``bench`` measures the parser.
"""
