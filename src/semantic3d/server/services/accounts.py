"""Accounts: argon2 passwords, login throttling, hashed API tokens, the admin role.

API tokens are ``s3d_`` + 43 URL-safe characters (256 random bits); only their sha256
is stored, so a leaked database does not leak tokens, and a plain hash suffices because
the secret has full entropy (no dictionary to attack, unlike passwords).

argon2 takes 64 MiB per hash: registration and login compute at most
``password_hash_concurrency`` hashes at once in a process (a request waits up to
``password_hash_wait_s`` for a slot, then gets 503), and registrations are throttled per
client address, so a burst of sign-ups cannot take the server's memory.
"""

from __future__ import annotations

import hashlib
import logging
import re
import secrets
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta
from functools import lru_cache

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import and_, delete, func, select, update
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.db import write_transaction
from semantic3d.server.errors import (
    AuthenticationError,
    InvalidInputError,
    NotFoundError,
    ServerError,
    ServiceUnavailableError,
    ThrottledError,
)
from semantic3d.server.models import ApiToken, LoginFailure, User, utc_now
from semantic3d.server.settings import Settings
from semantic3d.server.throttle import RateLimiter

logger = logging.getLogger(__name__)

TOKEN_PREFIX = "s3d_"
USERNAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_.-]{2,31}$")
MIN_PASSWORD_LENGTH = 8
MAX_PASSWORD_LENGTH = 1024
TOKEN_LAST_USED_EVERY = timedelta(minutes=1)
"""A token's "last used" time is written at most this often (not on every request)."""

_hasher = PasswordHasher()


@lru_cache(maxsize=1)
def dummy_hash() -> str:
    """A hash verified against for unknown usernames, so a wrong name costs as long as a
    wrong password. Made once per process: the server makes it at start-up
    (:func:`semantic3d.server.app.create_app`), so no login pays for it; the commands that
    import this module and log nobody in (an admin's ``create-token``) never do."""
    return _hasher.hash(secrets.token_urlsafe(16))


def normalise_username(username: str) -> str:
    """``username`` stripped and lower-cased (names are case-insensitive)."""
    return username.strip().lower()


def validate_username(username: str) -> str:
    """The normalised name, or :class:`InvalidInputError` saying what is allowed."""
    name = normalise_username(username)
    if not USERNAME_PATTERN.match(name):
        raise InvalidInputError(
            f"username {username!r}: expected 3-32 characters a-z, 0-9, '_', '.', '-', "
            "starting with a letter or digit"
        )
    return name


def validate_password(password: str) -> None:
    """Raise :class:`InvalidInputError` unless ``password`` has an acceptable length."""
    if not MIN_PASSWORD_LENGTH <= len(password) <= MAX_PASSWORD_LENGTH:
        raise InvalidInputError(
            f"password: expected {MIN_PASSWORD_LENGTH}..{MAX_PASSWORD_LENGTH} characters, "
            f"found {len(password)}"
        )


def hash_password(password: str) -> str:
    """The argon2id hash of ``password``."""
    return _hasher.hash(password)


def verify_password(password_hash: str, password: str) -> bool:
    """Whether ``password`` matches ``password_hash`` (never raises on a mismatch)."""
    try:
        return _hasher.verify(password_hash, password)
    except (VerificationError, InvalidHashError):
        return False


@lru_cache(maxsize=8)
def _hashing_slots(concurrency: int) -> threading.BoundedSemaphore:
    return threading.BoundedSemaphore(concurrency)


@contextmanager
def hashing_slot(settings: Settings) -> Iterator[None]:
    """Hold one of the process's ``password_hash_concurrency`` slots for a password hash.

    Raises :class:`ServiceUnavailableError` (503) when none frees up within
    ``password_hash_wait_s``.
    """
    slots = _hashing_slots(settings.password_hash_concurrency)
    if not slots.acquire(timeout=settings.password_hash_wait_s):
        raise ServiceUnavailableError(
            "the server is busy checking passwords; try again in a few seconds",
            retry_after_s=max(1, round(settings.password_hash_wait_s)),
        )
    try:
        yield
    finally:
        slots.release()


def register_user(
    factory: sessionmaker[Session],
    settings: Settings,
    limiter: RateLimiter,
    username: str,
    password: str,
    *,
    address: str,
) -> User:
    """Create an account from the registration form: throttled per address, hashing bounded.

    Every attempt from ``address`` counts (``register_max_per_ip`` per
    ``register_window_s``), checked before any hashing: a throttled attempt costs nothing.
    """
    limiter.check_and_hit(address[:64], "registrations from your address")
    name = validate_username(username)
    validate_password(password)
    with hashing_slot(settings):
        password_hash = hash_password(password)
    return _insert_user(factory, name, password_hash, is_admin=False)


def create_user(
    factory: sessionmaker[Session], username: str, password: str, *, is_admin: bool = False
) -> User:
    """Create an account; :class:`InvalidInputError` if the name is taken or invalid."""
    name = validate_username(username)
    validate_password(password)
    return _insert_user(factory, name, hash_password(password), is_admin=is_admin)


def _insert_user(
    factory: sessionmaker[Session], name: str, password_hash: str, *, is_admin: bool
) -> User:
    try:
        with write_transaction(factory) as session:
            user = User(username=name, password_hash=password_hash, is_admin=is_admin)
            session.add(user)
            session.flush()
    except IntegrityError:
        raise InvalidInputError(f"username {name!r} is already taken") from None
    logger.info("created account %s%s", name, " (admin)" if is_admin else "")
    return user


def set_admin(factory: sessionmaker[Session], username: str, *, is_admin: bool) -> User:
    """Grant or revoke the admin role."""
    with write_transaction(factory) as session:
        user = _user_by_name(session, username)
        user.is_admin = is_admin
    return user


def _user_by_name(session: Session, username: str) -> User:
    user = session.scalars(
        select(User).where(User.username == normalise_username(username))
    ).one_or_none()
    if user is None:
        raise NotFoundError(f"no account named {username!r}")
    return user


def authenticate(
    factory: sessionmaker[Session],
    settings: Settings,
    username: str,
    password: str,
    *,
    address: str,
) -> User:
    """The account for ``username``/``password``, with brute-force throttling.

    Failures are counted per account *and client address* (``login_max_failures``), per
    address (``login_max_failures_per_ip``) and per account from all addresses
    (``login_max_failures_per_account``, a higher cap against distributed guessing), so
    that one stranger cannot lock an account's owner out by failing a few logins.
    Every attempt is recorded (and committed) *before* it is counted and the password
    checked: of any number of concurrent guesses at most the limits get their password
    checked; the rest get :class:`ThrottledError` with a retry time. A throttled attempt's
    record is then dropped (it checked nothing), so hammering on does not prolong the
    lock past that time; a successful login deletes the account's records.
    """
    name = normalise_username(username)[:64]
    address = address[:64]
    now = utc_now()
    since = now - timedelta(seconds=settings.login_window_s)
    with write_transaction(factory) as session:
        session.execute(delete(LoginFailure).where(LoginFailure.at < since))
        attempt = LoginFailure(username=name, address=address, at=now)
        session.add(attempt)
        session.flush()
        attempt_id = attempt.id
    try:
        with factory() as session:
            _check_throttle(session, settings, name, address, since)
            user = session.scalars(select(User).where(User.username == name)).one_or_none()
    except ThrottledError:
        with write_transaction(factory) as session:
            session.execute(delete(LoginFailure).where(LoginFailure.id == attempt_id))
        raise
    try:
        with hashing_slot(settings):
            valid = verify_password(user.password_hash if user else dummy_hash(), password)
    except ServiceUnavailableError:  # nothing was checked: the attempt does not count
        with write_transaction(factory) as session:
            session.execute(delete(LoginFailure).where(LoginFailure.id == attempt_id))
        raise
    if valid and user is not None:
        with write_transaction(factory) as session:
            session.execute(delete(LoginFailure).where(LoginFailure.username == name))
        return user
    logger.info("failed login for %r from %s", name, address)
    raise AuthenticationError("wrong username or password")


def _check_throttle(
    session: Session, settings: Settings, name: str, address: str, since: datetime
) -> None:
    checks = (
        (
            and_(LoginFailure.username == name, LoginFailure.address == address),
            settings.login_max_failures,
            "this account from your address",
        ),
        (LoginFailure.address == address, settings.login_max_failures_per_ip, "your address"),
        (LoginFailure.username == name, settings.login_max_failures_per_account, "this account"),
    )
    for condition, limit, who in checks:
        # Counts this attempt too, hence ``>``: ``limit`` failures allowed per window.
        count, oldest = session.execute(
            select(func.count(), func.min(LoginFailure.at)).where(
                condition, LoginFailure.at >= since
            )
        ).one()
        if count > limit and oldest is not None:
            retry = oldest + timedelta(seconds=settings.login_window_s) - utc_now()
            retry_s = max(1, int(retry.total_seconds()) + 1)
            raise ThrottledError(
                f"too many login attempts for {who}: {count - 1} failed in the last "
                f"{max(1, settings.login_window_s // 60)} min; try again in {retry_s} s",
                retry_after_s=retry_s,
            )


def hash_token(secret: str) -> str:
    """The stored form of an API token (sha256, hex)."""
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def create_token(factory: sessionmaker[Session], user_id: int, name: str) -> tuple[ApiToken, str]:
    """A new API token for ``user_id``: the row and the secret (shown once, never stored)."""
    label = name.strip()[:100] or "token"
    secret = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with write_transaction(factory) as session:
        token = ApiToken(
            user_id=user_id, name=label, token_hash=hash_token(secret), prefix=secret[:10]
        )
        session.add(token)
        session.flush()
    return token, secret


def create_token_for(factory: sessionmaker[Session], username: str, name: str) -> str:
    """A new API token for the account ``username`` (admin command); returns the secret."""
    with factory() as session:
        user = _user_by_name(session, username)
    return create_token(factory, user.id, name)[1]


def user_for_token(factory: sessionmaker[Session], secret: str) -> User:
    """The account owning a valid, unrevoked token, or :class:`AuthenticationError`."""
    if not secret.startswith(TOKEN_PREFIX) or len(secret) > 100:
        raise AuthenticationError("invalid API token: expected 's3d_…' from your account page")
    with factory() as session:
        row = session.execute(
            select(ApiToken, User)
            .join(User, ApiToken.user_id == User.id)
            .where(ApiToken.token_hash == hash_token(secret), ApiToken.revoked_at.is_(None))
        ).one_or_none()
    if row is None:
        raise AuthenticationError("invalid or revoked API token")
    token, user = row
    now = utc_now()
    if token.last_used_at is None or now - token.last_used_at > TOKEN_LAST_USED_EVERY:
        # Bookkeeping only: a busy or full database must not turn a valid token away.
        try:
            with write_transaction(factory) as session:
                session.execute(
                    update(ApiToken).where(ApiToken.id == token.id).values(last_used_at=now)
                )
        except (ServerError, OperationalError) as exc:
            logger.warning("token %s: last use not recorded (%s)", token.prefix, exc)
    return user


def list_tokens(factory: sessionmaker[Session], user_id: int) -> list[ApiToken]:
    """The account's unrevoked tokens, newest first."""
    with factory() as session:
        return list(
            session.scalars(
                select(ApiToken)
                .where(ApiToken.user_id == user_id, ApiToken.revoked_at.is_(None))
                .order_by(ApiToken.id.desc())
            )
        )


def revoke_token(factory: sessionmaker[Session], user_id: int, token_id: int) -> None:
    """Revoke one of the account's tokens; :class:`NotFoundError` if it is not theirs."""
    with write_transaction(factory) as session:
        token = session.get(ApiToken, token_id)
        if token is None or token.user_id != user_id or token.revoked_at is not None:
            raise NotFoundError(f"token {token_id}: no such active token on your account")
        token.revoked_at = utc_now()


def end_sessions(factory: sessionmaker[Session], user_id: int) -> None:
    """Invalidate every session cookie of the account (logout)."""
    with write_transaction(factory) as session:
        session.execute(
            update(User)
            .where(User.id == user_id)
            .values(session_epoch=User.session_epoch + 1)
            .execution_options(synchronize_session=False)
        )


def get_user(factory: sessionmaker[Session], user_id: int) -> User | None:
    """The account with id ``user_id``, if it still exists."""
    with factory() as session:
        return session.get(User, user_id)
