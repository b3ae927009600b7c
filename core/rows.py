"""Reads on the hot path of every request, without the ORM compiling the same SQL each time.

A queryset builds its SQL anew on every evaluation: for a `get()` with `select_related` over
three models that is about 0.3 ms of CPU per call, ten times the query itself, and an upload
or a view makes several. `FixedSelect` writes one such SELECT once (from the models' own
metadata, so a new field is read without touching it) and turns each row into model
instances with Django's own converters and related-object caches, as the queryset would.
Only for reads whose shape never changes; everything else uses the ORM.
"""

from collections.abc import Sequence
from typing import Any, LiteralString

from django.db import connections, router
from django.db.models import Field, Model


class FixedSelect:
    """SELECT `model` WHERE `where` [ORDER BY `order_by`] [LIMIT `limit`], with the models of
    `related` (a chain of foreign keys from `model`, as `select_related("a__b")`) joined and
    cached on each instance. In `where` and `order_by` the tables are `t0` (`model`), `t1`,
    ... along the chain, and values are `%s` placeholders."""

    def __init__(
        self,
        model: type[Model],
        *,
        related: Sequence[str] = (),
        where: LiteralString,
        order_by: LiteralString = "",
        limit: int | None = None,
    ) -> None:
        self.model = model
        self.related = tuple(related)
        self.where = where
        self.order_by = order_by
        self.limit = limit
        self._chain = self._models_along(model, self.related)
        self._sql: dict[str, str] = {}
        self._converters: dict[str, list[list[Any]]] = {}

    @staticmethod
    def _models_along(
        model: type[Model], related: Sequence[str]
    ) -> list[tuple[type[Model], Field | None]]:
        """(model, the foreign key reaching the next one) along the chain; the last has None."""
        chain = []
        current = model
        for name in related:
            field = current._meta.get_field(name)
            chain.append((current, field))
            current = field.related_model
        chain.append((current, None))
        return chain

    def fetch(self, params: Sequence[object]) -> list[Model]:
        """The instances matching, in order."""
        alias = router.db_for_read(self.model)
        connection = connections[alias]
        sql = self._sql.get(alias) or self._sql.setdefault(alias, self._build(connection))
        with connection.cursor() as cursor:
            cursor.execute(sql, params)
            rows = cursor.fetchall()
        converters = self._converters.get(alias)
        if converters is None:
            converters = self._converters.setdefault(alias, self._converters_for(connection))
        return [self._instance(alias, connection, row, converters) for row in rows]

    def fetch_one(self, params: Sequence[object]) -> Model | None:
        found = self.fetch(params)
        return found[0] if found else None

    def _fields(self, model: type[Model]) -> list[Field]:
        return list(model._meta.concrete_fields)

    def _build(self, connection: Any) -> str:
        quote = connection.ops.quote_name
        columns = []
        joins = [f"{quote(self.model._meta.db_table)} t0"]
        for number, (model, foreign_key) in enumerate(self._chain):
            columns += [f"t{number}.{quote(f.column)}" for f in self._fields(model)]
            if foreign_key is not None:
                target = foreign_key.related_model
                joins.append(
                    f"INNER JOIN {quote(target._meta.db_table)} t{number + 1} ON "
                    f"t{number + 1}.{quote(foreign_key.target_field.column)} = "
                    f"t{number}.{quote(foreign_key.column)}"
                )
        # Names from the models' metadata, quoted; `where` and `order_by` are literals in the
        # code (LiteralString); values only ever travel as parameters.
        sql = f"SELECT {', '.join(columns)} FROM {' '.join(joins)} WHERE {self.where}"  # noqa: S608
        if self.order_by:
            sql += f" ORDER BY {self.order_by}"
        if self.limit is not None:
            sql += f" LIMIT {int(self.limit)}"
        return sql

    def _converters_for(self, connection: Any) -> list[list[Any]]:
        """Per column: (expression, converters), as the ORM's compiler applies them."""
        converters = []
        for number, (model, _foreign_key) in enumerate(self._chain):
            for field in self._fields(model):
                column = field.get_col(f"t{number}")
                found = connection.ops.get_db_converters(column) + column.get_db_converters(
                    connection
                )
                converters.append([column, found])
        return converters

    def _instance(
        self, alias: str, connection: Any, row: Sequence[object], converters: list[list[Any]]
    ) -> Model:
        values = list(row)
        for index, (column, found) in enumerate(converters):
            for converter in found:
                values[index] = converter(values[index], column, connection)
        instances = []
        start = 0
        for model, _foreign_key in self._chain:
            fields = self._fields(model)
            names = [field.attname for field in fields]
            instances.append(model.from_db(alias, names, values[start : start + len(fields)]))
            start += len(fields)
        for (_model, foreign_key), child, parent in zip(
            self._chain, instances, instances[1:], strict=False
        ):
            foreign_key.set_cached_value(child, parent)
        return instances[0]
