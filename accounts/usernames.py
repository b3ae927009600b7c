"""Usernames: what a new one may be, and when two look alike.

Envelopes and grants name owners by username, and a grant typed as `Alice` must not reach
a look-alike of `alice`. So a new username is refused when its skeleton (`username_skeleton`)
is an existing owner's, and an owner is resolved by name only when no other live owner has a
name of the same skeleton (sharing.selectors.grants.owner_resolve).

The rule is stricter than Unicode TR39's skeletons, whose data this portal does not ship: a
new username is ASCII only (letters, digits and @ . + - _), and two names are the same when
they are equal after case folding and after folding the ASCII look-alikes (0 and o; 1, i, l
and I; rn and m; vv and w). Names made before the rule (any Unicode letters, as Django's
default validator allowed) keep working; their skeleton also strips diacritics and folds
the Cyrillic and Greek letters that look like Latin ones, so that a new ASCII `alice` is
refused beside an old one spelt with a Cyrillic a.
"""

import re
import unicodedata

from accounts.errors import InvalidUsername

MAX_LENGTH = 150
_ALLOWED = re.compile(r"[A-Za-z0-9@.+_-]+")

# Letters of other scripts drawn like Latin ones (lower case: the skeleton is case-folded).
_LATIN_LOOKALIKES = str.maketrans(
    {
        "\N{CYRILLIC SMALL LETTER A}": "a",
        "\N{CYRILLIC SMALL LETTER VE}": "b",
        "\N{CYRILLIC SMALL LETTER IE}": "e",
        "\N{CYRILLIC SMALL LETTER IO}": "e",
        "\N{CYRILLIC SMALL LETTER SHHA}": "h",
        "\N{CYRILLIC SMALL LETTER BYELORUSSIAN-UKRAINIAN I}": "i",
        "\N{CYRILLIC SMALL LETTER YI}": "i",
        "\N{CYRILLIC SMALL LETTER JE}": "j",
        "\N{CYRILLIC SMALL LETTER KA}": "k",
        "\N{CYRILLIC SMALL LETTER EM}": "m",
        "\N{CYRILLIC SMALL LETTER EN}": "h",
        "\N{CYRILLIC SMALL LETTER O}": "o",
        "\N{CYRILLIC SMALL LETTER ER}": "p",
        "\N{CYRILLIC SMALL LETTER ES}": "c",
        "\N{CYRILLIC SMALL LETTER TE}": "t",
        "\N{CYRILLIC SMALL LETTER U}": "y",
        "\N{CYRILLIC SMALL LETTER HA}": "x",
        "\N{CYRILLIC SMALL LETTER DZE}": "s",
        "\N{CYRILLIC SMALL LETTER KOMI DE}": "d",
        "\N{CYRILLIC SMALL LETTER QA}": "q",
        "\N{CYRILLIC SMALL LETTER WE}": "w",
        "\N{LATIN SMALL LETTER SCRIPT G}": "g",
        "\N{CYRILLIC SMALL LETTER PALOCHKA}": "l",
        "\N{CYRILLIC SMALL LETTER PE}": "n",
        "\N{GREEK SMALL LETTER ALPHA}": "a",
        "\N{GREEK SMALL LETTER BETA}": "b",
        "\N{GREEK SMALL LETTER EPSILON}": "e",
        "\N{GREEK SMALL LETTER ETA}": "n",
        "\N{GREEK SMALL LETTER IOTA}": "i",
        "\N{GREEK SMALL LETTER KAPPA}": "k",
        "\N{GREEK SMALL LETTER NU}": "v",
        "\N{GREEK SMALL LETTER OMICRON}": "o",
        "\N{GREEK SMALL LETTER RHO}": "p",
        "\N{GREEK SMALL LETTER TAU}": "t",
        "\N{GREEK SMALL LETTER UPSILON}": "u",
        "\N{GREEK SMALL LETTER CHI}": "x",
        "\N{GREEK SMALL LETTER OMEGA}": "w",
        "\N{GREEK LUNATE SIGMA SYMBOL}": "c",
        "\N{GREEK LETTER YOT}": "j",
    }
)
# ASCII look-alikes, folded after the other scripts' into one of each group.
_ASCII_LOOKALIKES = str.maketrans({"0": "o", "1": "l", "i": "l", "|": "l"})
_SEQUENCES = (("rn", "m"), ("vv", "w"))


def username_skeleton(username: str) -> str:
    """What the name looks like: compatibility-normalised, diacritics stripped, case-folded,
    look-alike letters and sequences folded. Two names with one skeleton are confusable."""
    decomposed = unicodedata.normalize("NFKD", username)
    bare = "".join(c for c in decomposed if not unicodedata.combining(c))
    folded = unicodedata.normalize("NFKC", bare).casefold()
    folded = folded.translate(_LATIN_LOOKALIKES).translate(_ASCII_LOOKALIKES)
    for sequence, letter in _SEQUENCES:
        folded = folded.replace(sequence, letter)
    return folded


def username_check(username: str) -> None:
    """InvalidUsername unless the name may be given to a new owner: 1 to MAX_LENGTH characters,
    ASCII letters, digits and @ . + - _."""
    if not username or len(username) > MAX_LENGTH:
        raise InvalidUsername(f"a username has 1 to {MAX_LENGTH} characters")
    if not _ALLOWED.fullmatch(username):
        raise InvalidUsername(
            "a username is made of ASCII letters, digits and @ . + - _ only (names in other "
            "scripts can be told apart from look-alikes only by their script's rules)"
        )
