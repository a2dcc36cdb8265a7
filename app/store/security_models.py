"""SQLAlchemy models of the security tables: browser sessions, one-time login codes, the
people who sign in through single sign-on, the cluster's signing secret and the write rate
limit's log."""

from __future__ import annotations

from sqlalchemy import Double, ForeignKey, Index, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from eqgw.store.models import Base, JSONDict, JsonType


class BrowserSession(Base):
    """A dashboard login: a cookie's SHA-256 standing for one API key until logout or expiry.

    The key is resolved on every request (cached briefly), so revoking the key ends its
    sessions; deleting the row (logout) ends this one. A single sign-on session stands for a
    person (`person_id`) and carries the role and scope their groups gave at sign-in
    (`grants`); its key is the person's own (`SsoPerson.key_id`), which no request can present.
    """

    __tablename__ = "browser_sessions"
    __table_args__ = (Index(None, "key_id"), Index(None, "expires_at"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    key_id: Mapped[int] = mapped_column(Integer, ForeignKey("api_keys.id", ondelete="CASCADE"))
    csrf_token: Mapped[str] = mapped_column(String(64), doc="sent back in X-CSRF-Token on writes")
    created_at: Mapped[float] = mapped_column(Double)
    expires_at: Mapped[float] = mapped_column(Double)
    person_id: Mapped[int | None] = mapped_column(
        Integer,
        ForeignKey("sso_people.id", ondelete="CASCADE"),
        doc="the person of a single sign-on session (null: a key's login)",
    )
    grants: Mapped[list[JSONDict] | None] = mapped_column(
        JsonType, doc="[{role, groups, vehicles}] from the groups at sign-in (null: the key's)"
    )


class SsoPerson(Base):
    """A person who signed in through the OpenID provider: issuer and subject (the ID token's
    `iss` and `sub`), the email and name it last gave, and the key row standing for them.

    The key row gives the person what a key has (an id for the audit log and the write rate
    limit, a revocation that ends every session); its secret is never made, so only their
    sessions use it. Revoked, the next sign-in gets a new key row.
    """

    __tablename__ = "sso_people"
    __table_args__ = (UniqueConstraint("issuer", "subject"), Index(None, "key_id"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    issuer: Mapped[str] = mapped_column(String(500))
    subject: Mapped[str] = mapped_column(String(255))
    email: Mapped[str | None] = mapped_column(String(320))
    name: Mapped[str | None] = mapped_column(String(200))
    key_id: Mapped[int] = mapped_column(Integer, ForeignKey("api_keys.id", ondelete="CASCADE"))
    created_at: Mapped[float] = mapped_column(Double)
    last_login_at: Mapped[float] = mapped_column(Double)


class ClusterSecret(Base):
    """The secret gateways sign their NOTIFY payloads with (one row, made by the first gateway).

    LISTEN/NOTIFY needs no table privilege: a database role that cannot read this table
    cannot forge what gateways accept.
    """

    __tablename__ = "cluster_secrets"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    secret: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[float] = mapped_column(Double)


class WriteBudget(Base):
    """One row per key that has written: the row its rate-limit checks lock, so the checks of
    one key, on any gateway of the database, run one at a time."""

    __tablename__ = "write_budgets"

    key_id: Mapped[int] = mapped_column(
        Integer,
        ForeignKey("api_keys.id", ondelete="CASCADE"),
        primary_key=True,
        autoincrement=False,
    )
    checked_at: Mapped[float] = mapped_column(Double, doc="the latest check (the database's clock)")


class WriteHit(Base):
    """A write counted against its key's limit, kept for one window (the sliding window's log)."""

    __tablename__ = "write_hits"
    __table_args__ = (Index(None, "key_id", "ts"), Index(None, "ts"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    key_id: Mapped[int] = mapped_column(Integer, ForeignKey("api_keys.id", ondelete="CASCADE"))
    ts: Mapped[float] = mapped_column(Double)


class LoginCode(Base):
    """A one-time dashboard login code: its SHA-256, the key it logs in as, until when.

    Consumed by deleting the row (one statement), so it works once, on any gateway.
    """

    __tablename__ = "login_codes"
    __table_args__ = (Index(None, "key_id"), Index(None, "expires_at"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    code_hash: Mapped[str] = mapped_column(String(64), unique=True)
    key_id: Mapped[int] = mapped_column(Integer, ForeignKey("api_keys.id", ondelete="CASCADE"))
    created_at: Mapped[float] = mapped_column(Double)
    expires_at: Mapped[float] = mapped_column(Double)
