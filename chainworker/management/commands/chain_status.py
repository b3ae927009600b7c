"""`manage.py chain_status`: node, chain id, latest block, contract, admin, operator balance,
and whether the node is still the chain the contract was deployed on (a reset stops sending)
and still makes blocks (a stall pauses sending)."""

import json
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser
from web3 import Web3

from chainworker.errors import ChainError
from chainworker.services import chain_status


class Command(BaseCommand):
    help = "Show the chain node, contract and operator account the portal uses."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--json", action="store_true", help="print the status as JSON")

    def handle(self, *args: Any, **options: Any) -> None:
        try:
            status = chain_status()
        except ChainError as exc:
            raise CommandError(f"chain unavailable: {exc}") from exc
        if options["json"]:
            self.stdout.write(json.dumps(status, sort_keys=True))
            return
        balance = Web3.from_wei(int(status["operator_balance_wei"]), "ether")
        rows = [
            ("node", status["node_url"]),
            ("client", status["client_version"]),
            ("chain id", status["chain_id"]),
            ("chain identity", status.get("chain_identity", "-")),
            ("latest block", status["latest_block"]),
            ("since last block", f"{status.get('seconds_since_block', '-')} s"),
            ("chain stalled", "yes" if status.get("chain_stalled") else "no"),
            ("contract", status["contract_address"] or "not deployed"),
            ("admin", status["admin"] or "-"),
            ("records anchored", status.get("record_count", "-")),
            ("operator", status["operator"]),
            ("operator balance", f"{balance} ETH"),
            ("confirmations", status["confirmations"]),
        ]
        for label, value in rows:
            self.stdout.write(f"{label:>17}: {value}")
        if "problem" in status:
            self.stderr.write(self.style.WARNING(str(status["problem"])))
