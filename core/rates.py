"""Rates written as DRF writes them: "<requests>/<second|minute|hour|day>"."""

_PERIOD_SECONDS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def rate_parse(rate: str) -> tuple[int, int]:
    """(requests, seconds) of a rate such as "600/minute" or "5/hour"."""
    count, _, period = rate.partition("/")
    try:
        return int(count), _PERIOD_SECONDS[period.strip()[:1]]
    except (ValueError, KeyError):
        raise ValueError(f"a rate is <number>/<second|minute|hour|day>, not {rate!r}") from None
