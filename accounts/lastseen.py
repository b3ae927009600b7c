"""How long ago a robot was last heard of, in the words the robot pages and their poll show.

One wording for the robots table, the robot page and its status poll (the JSON carries the
text, so the page's script never words it again).
"""

from datetime import datetime


def seen_ago_text(moment: datetime | None, *, now: datetime) -> str:
    """ "2 s ago", "5 min ago", "3 h ago", "2 days ago"; "never" for no moment. A moment
    ahead of `now` (a robot's clock ahead of the portal's) is "just now"."""
    if moment is None:
        return "never"
    seconds = int((now - moment).total_seconds())
    if seconds < 1:
        return "just now"
    if seconds < 120:
        return f"{seconds} s ago"
    if seconds < 2 * 3600:
        return f"{seconds // 60} min ago"
    if seconds < 2 * 86400:
        return f"{seconds // 3600} h ago"
    return f"{seconds // 86400} days ago"
