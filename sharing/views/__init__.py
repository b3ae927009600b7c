"""Owner pages of the sharing app, one module per page group (routes: sharing/urls.py).

- records.py: the record lists: my records, and records shared with me.
- record.py: one record: its page (the verdict first, then the content and the trajectory
  plot of an odometry record), its raw JSON download, and an image topic's gallery.
- deletion.py: deleting a record, a selection of records, or the whole account (here rather
  than in accounts: it deletes records and revokes grants too).
- grants.py: giving access, changing a grant's terms, revoking.
- audit.py: the audit trail (the owner's transactions and anchoring).
- access_log.py: the access log page and its CSV download.
- tokens.py: revoking an owner API token, and what it granted (here rather than in accounts:
  the page lists and revokes the grants the token made).
- exports.py: exporting a selection, an export's progress, rebuilding one.
- robot.py: the robot page (is it alive, what it sends, its latest verified pose and image).
- filters.py: what a list page says of the filters it left out.

A record's content is only ever shown through `records_open` (`record_open` for one): the
worker checks access and the stored ciphertext's SM3 digest against the chain, and the
content is decrypted only when the verdict is `verified`. How the content is shown is
sharing/content.py; the audit trail's entries are sharing/audit.py.

Import from the module that serves the page; this package re-exports nothing.
"""
