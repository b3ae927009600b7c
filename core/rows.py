"""Reads and writes on the hot path of every request, without the ORM compiling the same SQL
each time.

A queryset builds its SQL anew on every evaluation: for a `get()` with `select_related` over
three models that is about 0.3 ms of CPU per call, ten times the query itself, and an upload
or a view makes several. `FixedSelect` writes one such SELECT once (from the models' own
metadata, so a new field is read without touching it) and turns each row into model
instances with Django's own converters and related-object caches, as the queryset would.
`FixedInsert` and `FixedUpdate` do the same for an upload's writes: whole new rows, and one
UPDATE of set columns under a fixed condition. Only for statements whose shape never changes;
everything else uses the ORM.
"""

import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, LiteralString

from django.db import connections, router
from django.db.models import AutoField, DateTimeField, Field, ForeignKey, Model, UUIDField
from django.db.models.base import ModelState
from django.db.models.signals import post_init, pre_init
from django.utils import timezone


def _built(cache: dict[Any, Any], key: Any, build: Callable[[], Any]) -> Any:
    """What `cache` holds under `key` (an alias, or an alias and a row count), built once."""
    found = cache.get(key)
    return found if found is not None else cache.setdefault(key, build())


def _prepared(
    fields: Sequence[Field], values: Sequence[object], connection: Any, *, saved: bool = False
) -> list[object]:
    """Each value as the database takes it for its field: to compare with, or `saved` into a
    column."""
    return [
        field.get_db_prep_save(value, connection)
        if saved
        else field.get_db_prep_value(value, connection)
        for field, value in zip(fields, values, strict=True)
    ]


@dataclass(frozen=True)
class _Table:
    """One model in the SELECT: its alias, and the foreign key (of the table at `parent`)
    that reaches it; the first table has neither."""

    model: type[Model]
    alias: str
    parent: int | None = None
    foreign_key: Field | None = None


class FixedSelect:
    """SELECT `model` WHERE `where` [ORDER BY `order_by`] [LIMIT `limit`], with the models of
    `related` joined and cached on each instance, as `select_related(*related)` (paths such as
    "owner__user"; a nullable key is a LEFT JOIN and caches None). In `where` and `order_by`
    `t0` is `model`'s table, `t1`, `t2`... the related ones in the order named; values are
    `%s` placeholders, one per name in `params_of`: the fields of `model` each value is
    prepared for the database as (a UUID, a boolean...)."""

    def __init__(
        self,
        model: type[Model],
        *,
        related: Sequence[str] = (),
        where: LiteralString,
        params_of: Sequence[str],
        order_by: LiteralString = "",
        limit: int | None = None,
    ) -> None:
        self.model = model
        self._params_of = [model._meta.get_field(name) for name in params_of]
        self.where = where
        self.order_by = order_by
        self.limit = limit
        self._tables = self._tables_for(model, related)
        self._sql: dict[str, str] = {}
        self._converters: dict[str, list[tuple[Any, list[Any]]]] = {}

    @staticmethod
    def _tables_for(model: type[Model], related: Sequence[str]) -> list[_Table]:
        tables = [_Table(model, "t0")]
        by_path = {"": 0}
        for path in related:
            walked = ""
            for name in path.split("__"):
                parent = by_path[walked]
                walked = f"{walked}__{name}" if walked else name
                if walked not in by_path:
                    field = tables[parent].model._meta.get_field(name)
                    by_path[walked] = len(tables)
                    tables.append(_Table(field.related_model, f"t{len(tables)}", parent, field))
        return tables

    def fetch(self, *values: object) -> list[Model]:
        """The instances matching `values` (one per `params_of`), in order."""
        alias = router.db_for_read(self.model)
        connection = connections[alias]
        sql = _built(self._sql, alias, lambda: self._build(connection))
        with connection.cursor() as cursor:
            cursor.execute(sql, _prepared(self._params_of, values, connection))
            rows = cursor.fetchall()
        converters = _built(self._converters, alias, lambda: self._converters_for(connection))
        return [self._instance(alias, connection, row, converters) for row in rows]

    def fetch_one(self, *values: object) -> Model | None:
        found = self.fetch(*values)
        return found[0] if found else None

    def get(self, *values: object) -> Model:
        """fetch_one, raising the model's DoesNotExist when nothing matches (as `get()`)."""
        found = self.fetch_one(*values)
        if found is None:
            raise self.model.DoesNotExist(f"no {self.model._meta.verbose_name} matches")
        return found

    @staticmethod
    def _fields(model: type[Model]) -> list[Field]:
        return list(model._meta.concrete_fields)

    def _build(self, connection: Any) -> str:
        quote = connection.ops.quote_name
        columns = [
            f"{table.alias}.{quote(field.column)}"
            for table in self._tables
            for field in self._fields(table.model)
        ]
        joins = [f"{quote(self.model._meta.db_table)} t0"]
        for table in self._tables[1:]:
            key, parent = table.foreign_key, self._tables[table.parent]
            join = "LEFT OUTER JOIN" if key.null else "INNER JOIN"
            joins.append(
                f"{join} {quote(table.model._meta.db_table)} {table.alias} ON "
                f"{table.alias}.{quote(key.target_field.column)} = "
                f"{parent.alias}.{quote(key.column)}"
            )
        # Names from the models' metadata, quoted; `where` and `order_by` are literals in the
        # code (LiteralString); values only ever travel as parameters.
        sql = f"SELECT {', '.join(columns)} FROM {' '.join(joins)} WHERE {self.where}"  # noqa: S608
        if self.order_by:
            sql += f" ORDER BY {self.order_by}"
        if self.limit is not None:
            sql += f" LIMIT {int(self.limit)}"
        return sql

    def _converters_for(self, connection: Any) -> list[tuple[Any, list[Any]]]:
        """Per column: (expression, converters), as the ORM's compiler applies them."""
        converters = []
        for table in self._tables:
            for field in self._fields(table.model):
                column = field.get_col(table.alias)
                found = connection.ops.get_db_converters(column) + column.get_db_converters(
                    connection
                )
                converters.append((column, found))
        return converters

    def _instance(
        self,
        alias: str,
        connection: Any,
        row: Sequence[object],
        converters: list[tuple[Any, list[Any]]],
    ) -> Model:
        values = list(row)
        for index, (column, found) in enumerate(converters):
            if values[index] is None:
                continue  # NULL: no converter of the ORM's changes it
            for converter in found:
                values[index] = converter(values[index], column, connection)
        instances: list[Model | None] = []
        start = 0
        for table in self._tables:
            fields = self._fields(table.model)
            own = values[start : start + len(fields)]
            start += len(fields)
            parent = None if table.parent is None else instances[table.parent]
            pk_index = fields.index(table.model._meta.pk)
            if table.parent is not None and (parent is None or own[pk_index] is None):
                instances.append(None)  # LEFT JOIN found nothing (or its parent is None)
            else:
                names = [field.attname for field in fields]
                instances.append(table.model.from_db(alias, names, own))
            if table.foreign_key is not None and parent is not None:
                table.foreign_key.set_cached_value(parent, instances[-1])
        return instances[0]


def instances_made(
    model: type[Model], names: Sequence[str], rows: Sequence[Sequence[object]], *, alias: str | None
) -> list[Model]:
    """Instances of `model`, one per row of values of the fields (attnames) `names`, in
    order: as read from database `alias` (Model.from_db's; the fields not named are deferred,
    read on first use, as `only()` leaves them), or new ones (`alias` None: every concrete
    field named). The values are taken as they are, as Model.__init__'s positional path takes
    them, without its per-field work (a check makes thousands: bench/REPORT.md); a model with
    receivers of pre_init or post_init gets Model.__init__ itself."""
    if pre_init.has_listeners(model) or post_init.has_listeners(model):
        return _instances_by_init(model, names, rows, alias=alias)
    made = []
    new = model.__new__
    for row in rows:
        instance = new(model)
        instance.__dict__.update(zip(names, row, strict=True))
        state = instance._state = ModelState()
        if alias is not None:
            state.adding, state.db = False, alias
        made.append(instance)
    return made


def _instances_by_init(
    model: type[Model], names: Sequence[str], rows: Sequence[Sequence[object]], *, alias: str | None
) -> list[Model]:
    if alias is not None:
        return [model.from_db(alias, names, row) for row in rows]
    return [model(**dict(zip(names, row, strict=True))) for row in rows]


class FixedInsert:
    """INSERT whole new instances of `model`, as `bulk_create` does (each field's `pre_save`,
    so `auto_now_add` applies; no signals), with the SQL written once per number of rows. The
    instances carry their primary key, or (an automatic one) are given it by the INSERT's
    RETURNING, in order, as bulk_create gives it on PostgreSQL and SQLite; a backend that
    cannot return rows from an INSERT gets bulk_create itself."""

    def __init__(self, model: type[Model]) -> None:
        self.model = model
        self._auto = model._meta.pk if isinstance(model._meta.pk, AutoField) else None
        self._fields = [field for field in model._meta.concrete_fields if field is not self._auto]
        # Per field, how a str or int value reaches the database when the field's own chain
        # of methods (pre_save, get_db_prep_save, get_prep_value, ...) would hand it on
        # unchanged: 13 fields of 100 rows are 1,300 such chains an upload.
        self._plain = [_plain_saved(field) for field in self._fields]
        self._sql: dict[tuple[str, int], str] = {}

    def insert(self, instances: Sequence[Model]) -> None:
        alias = router.db_for_write(self.model)
        connection = connections[alias]
        if self._auto is not None and not connection.features.can_return_rows_from_bulk_insert:
            self.model._default_manager.bulk_create(instances)
            return
        size = max(1, connection.ops.bulk_batch_size(self._fields, instances) or len(instances))
        for start in range(0, len(instances), size):
            chunk = instances[start : start + size]
            params = [
                self._saved(field, plain, instance, connection)
                for instance in chunk
                for field, plain in zip(self._fields, self._plain, strict=True)
            ]
            rows = len(chunk)
            sql = _built(self._sql, (alias, rows), lambda rows=rows: self._build(connection, rows))
            with connection.cursor() as cursor:
                cursor.execute(sql, params)
                if self._auto is not None:
                    for instance, (pk,) in zip(chunk, cursor.fetchall(), strict=True):
                        instance.pk = pk
        for instance in instances:
            instance._state.adding = False
            instance._state.db = alias

    @staticmethod
    def _saved(field: Field, plain: str | None, instance: Model, connection: Any) -> object:
        """The value of `field` as the database takes it for a new row of `instance`."""
        if plain is not None:
            if plain == _NOW:  # auto_now(_add) on a new row: pre_save's moment, as it sets it
                moment = instance.__dict__[field.attname] = timezone.now()
                return connection.ops.adapt_datetimefield_value(moment)
            value = instance.__dict__.get(field.attname)
            kind = type(value)
            if kind is str and plain == _TEXT:
                return value
            if kind is uuid.UUID and plain == _UUID:  # as UUIDField's get_db_prep_value ends
                return value if connection.features.has_native_uuid_field else value.hex
            if kind is int and plain == _KEY:
                return connection.ops.validate_autopk_value(value)  # as AutoField ends
            if kind is int and plain not in (_TEXT, _UUID):
                return connection.ops.adapt_integerfield_value(value, plain)
        return field.get_db_prep_save(field.pre_save(instance, True), connection)

    def _build(self, connection: Any, rows: int) -> str:
        quote = connection.ops.quote_name
        columns = ", ".join(quote(field.column) for field in self._fields)
        row = f"({', '.join(['%s'] * len(self._fields))})"
        table = quote(self.model._meta.db_table)
        returning = f" RETURNING {quote(self._auto.column)}" if self._auto is not None else ""
        return f"INSERT INTO {table} ({columns}) VALUES {', '.join([row] * rows)}{returning}"  # noqa: S608


_TEXT = "text"
_KEY = "key"  # a foreign key to an automatic primary key (AutoField's kind)
_UUID = "uuid"  # a UUIDField, or a foreign key to one
_NOW = "now"  # a DateTimeField set to the moment of its save (auto_now or auto_now_add)
_AUTO_TYPES = frozenset({"AutoField", "BigAutoField", "SmallAutoField"})
_INTEGER_TYPES = frozenset(
    {
        "IntegerField",
        "BigIntegerField",
        "SmallIntegerField",
        "PositiveIntegerField",
        "PositiveBigIntegerField",
        "PositiveSmallIntegerField",
    }
)


def _plain_saved(field: Field) -> str | None:
    """`_TEXT` for a field that saves a str as it is (CharField, TextField), the internal type
    of an integer field (an int goes to the backend's adapt_integerfield_value, as the
    field's own get_db_prep_value ends), `_KEY` for a ForeignKey to an automatic primary key
    (an int goes to the backend's validate_autopk_value, as AutoField's ends), `_UUID` for a
    UUIDField or a ForeignKey to one (a UUID goes as the backend takes it, as UUIDField's
    ends), `_NOW` for a DateTimeField of auto_now or auto_now_add (a new row's: the moment,
    set on the instance and adapted as the field's pre_save and get_db_prep_value do), None
    for any other (the field's own methods). Only the exact classes: a subclass may convert in its
    own way."""
    kind = type(field).__name__
    if type(field) is ForeignKey:
        target = field.target_field
        exact = type(target).__module__ == "django.db.models.fields"
        if exact and type(target).__name__ in _AUTO_TYPES:
            return _KEY
        return _UUID if type(target) is UUIDField else None
    if type(field).__module__ != "django.db.models.fields":
        return None
    if type(field) is UUIDField:
        return _UUID
    if type(field) is DateTimeField and (field.auto_now or field.auto_now_add):
        return _NOW
    if kind in ("CharField", "TextField"):
        return _TEXT
    if kind in _INTEGER_TYPES:
        return kind
    return None


class FixedUpdate:
    """UPDATE `model` SET the `columns` WHERE `where`, the SQL written once: `where` is a
    literal in the code with `%s` placeholders, one per name in `params_of` (the fields each
    value is prepared as). `run` answers the number of rows changed."""

    def __init__(
        self,
        model: type[Model],
        *,
        columns: Sequence[str],
        where: LiteralString,
        params_of: Sequence[str],
    ) -> None:
        self.model = model
        self._columns = [model._meta.get_field(name) for name in columns]
        self._params_of = [model._meta.get_field(name) for name in params_of]
        self.where = where
        self._sql: dict[str, str] = {}

    def run(self, values: Sequence[object], where: Sequence[object]) -> int:
        """Set the columns to `values` where `where` (one per `params_of`) holds."""
        alias = router.db_for_write(self.model)
        connection = connections[alias]
        sql = _built(self._sql, alias, lambda: self._build(connection))
        params = [
            *_prepared(self._columns, values, connection, saved=True),
            *_prepared(self._params_of, where, connection),
        ]
        with connection.cursor() as cursor:
            cursor.execute(sql, params)
            return cursor.rowcount

    def _build(self, connection: Any) -> str:
        quote = connection.ops.quote_name
        assignments = ", ".join(f"{quote(field.column)} = %s" for field in self._columns)
        table = quote(self.model._meta.db_table)
        return f"UPDATE {table} SET {assignments} WHERE {self.where}"  # noqa: S608
