"""The test process's password hasher: PBKDF2-SHA256 at few iterations.

Django's own does 1,000,000 iterations, 0.3-0.45 s of CPU on this machine, and the suite makes
an owner, with a password, in most of its tests. What this one makes is an ordinary
`pbkdf2_sha256$<iterations>$...` hash: the portal's hasher in a web process a test starts
checks it at the iterations it names (and re-hashes it at full strength on that login). The
portal's own settings are untouched (tests/portal/test_password_hashing.py).
"""

from django.contrib.auth.hashers import PBKDF2PasswordHasher


class FewIterationsPBKDF2PasswordHasher(PBKDF2PasswordHasher):
    iterations = 1_000
