"""The OpenID provider as a gateway uses it (single sign-on, eqgw.security.oidc): discovery,
keys, the authorization address, the code exchange and the ID token's checks.

Apart from the routes because it loads authlib, joserfc and httpx (0.1-0.3 s of CPU): a gateway
loads it only when single sign-on is set up."""

from __future__ import annotations

import asyncio
import ssl
import time
from collections.abc import Mapping
from typing import Any

import httpx
from authlib.oauth2.auth import ClientAuth
from authlib.oauth2.rfc6749.parameters import prepare_grant_uri, prepare_token_request
from authlib.oauth2.rfc7636 import create_s256_code_challenge
from authlib.oidc.core import CodeIDToken
from joserfc import jwt
from joserfc.errors import (
    BadSignatureError,
    ExpiredTokenError,
    InvalidClaimError,
    InvalidKeyIdError,
    JoseError,
    MissingClaimError,
)
from joserfc.jwk import KeySet
from joserfc.jws import JWSRegistry

from eqgw.config import OidcSettings
from eqgw.security.oidc import (
    Identity,
    LoginState,
    SignInRefused,
    _said,
    _unavailable,
    claim_values,
)

# ID token signatures accepted: the provider's published keys, never a shared secret.
ASYMMETRIC_ALGORITHMS = frozenset(
    {"RS256", "RS384", "RS512", "PS256", "PS384", "PS512", "ES256", "ES384", "ES512", "EdDSA"}
)
_METADATA_TTL_S = 3600.0


class OidcProvider:
    """The OpenID provider as this gateway uses it: its discovery document and keys (cached),
    the authorization address, the code exchange and the ID token's checks.

    Holds nothing open: each exchange with the provider has its own short-lived HTTP client
    (a sign-in is rare; a connection kept would only go stale).
    """

    def __init__(self, settings: OidcSettings) -> None:
        if not settings.issuer or not settings.client_id:
            raise ValueError("single sign-on needs oidc.issuer and oidc.client_id")
        self.settings = settings
        self.issuer: str = settings.issuer
        self.client_id: str = settings.client_id
        self._metadata: dict[str, Any] | None = None
        self._metadata_until = 0.0
        self._keys: KeySet | None = None
        self._lock = asyncio.Lock()
        self._tls_context: ssl.SSLContext | None = None

    def _tls(self) -> ssl.SSLContext:
        """The TLS context of every call to the provider, built once: building one loads a CA
        bundle (15-20 ms of CPU on the event loop), and a sign-in makes several calls."""
        if self._tls_context is None:
            ca_file = self.settings.ca_file
            if ca_file:
                self._tls_context = ssl.create_default_context(cafile=ca_file)
            else:
                self._tls_context = httpx.create_ssl_context()
        return self._tls_context

    def _http(self) -> httpx.AsyncClient:
        return httpx.AsyncClient(
            timeout=self.settings.timeout_s,
            verify=self._tls(),
            follow_redirects=False,
            headers={"Accept": "application/json"},
        )

    async def _get_json(self, url: str, headers: Mapping[str, str] | None = None) -> dict[str, Any]:
        try:
            async with self._http() as http:
                r = await http.get(url, headers=headers)
        except httpx.HTTPError as exc:
            raise _unavailable(f"{url} does not answer ({_said(exc)})") from exc
        if r.status_code != 200:
            raise _unavailable(f"{url} answered HTTP {r.status_code}")
        try:
            body = r.json()
        except ValueError as exc:
            raise _unavailable(f"{url} answered something other than JSON") from exc
        if not isinstance(body, dict):
            raise _unavailable(f"{url} answered something other than a JSON object")
        return body

    async def metadata(self) -> dict[str, Any]:
        """The provider's discovery document (read again after an hour)."""
        async with self._lock:
            if self._metadata is not None and time.monotonic() < self._metadata_until:
                return self._metadata
            url = self.issuer.rstrip("/") + "/.well-known/openid-configuration"
            doc = await self._get_json(url)
            if doc.get("issuer") != self.issuer:
                raise _unavailable(
                    f"{url} names the issuer {doc.get('issuer')!r}, not {self.issuer!r} "
                    "(oidc.issuer must be exactly the provider's)"
                )
            for name in ("authorization_endpoint", "token_endpoint", "jwks_uri"):
                if not isinstance(doc.get(name), str):
                    raise _unavailable(f"{url} names no {name}")
            self._metadata = doc
            self._metadata_until = time.monotonic() + _METADATA_TTL_S
            return doc

    async def keys(self, *, refresh: bool = False) -> KeySet:
        """The provider's published signing keys (read again when a token names another)."""
        if self._keys is not None and not refresh:
            return self._keys
        url = (await self.metadata())["jwks_uri"]
        doc = await self._get_json(url)
        try:
            self._keys = KeySet.import_key_set(doc)  # type: ignore[arg-type]
        except (JoseError, ValueError, KeyError, TypeError) as exc:
            raise _unavailable(f"its keys ({url}) cannot be read: {exc}") from exc
        return self._keys

    async def authorization_url(self, redirect_uri: str, login: LoginState) -> str:
        """Where the browser signs in: the authorization request of `login`."""
        meta = await self.metadata()
        uri: str = prepare_grant_uri(
            meta["authorization_endpoint"],
            client_id=self.client_id,
            response_type="code",
            redirect_uri=redirect_uri,
            scope=self.settings.scopes,
            state=login.state,
            nonce=login.nonce,
            code_challenge=create_s256_code_challenge(login.verifier),
            code_challenge_method="S256",
        )
        return uri

    async def exchange(self, code: str, login: LoginState, redirect_uri: str) -> dict[str, Any]:
        """The token endpoint's answer for a code (it holds an ID token)."""
        url = (await self.metadata())["token_endpoint"]
        body = prepare_token_request(
            "authorization_code", code=code, redirect_uri=redirect_uri, code_verifier=login.verifier
        )
        secret = self.settings.client_secret
        auth = ClientAuth(self.client_id, secret, "client_secret_basic" if secret else "none")
        headers = {"Content-Type": "application/x-www-form-urlencoded"}
        _, headers, body = auth.prepare("POST", url, headers, body)
        try:
            async with self._http() as http:
                r = await http.post(url, content=body, headers=headers)
        except httpx.HTTPError as exc:
            raise _unavailable(f"{url} does not answer ({_said(exc)})") from exc
        try:
            answer = r.json()
        except ValueError:
            answer = None
        if not isinstance(answer, dict):
            raise _unavailable(f"{url} answered HTTP {r.status_code} without a JSON object")
        if r.status_code != 200 or "error" in answer:
            said = str(answer.get("error", f"HTTP {r.status_code}"))
            if answer.get("error_description"):
                said += f": {answer['error_description']}"
            raise SignInRefused(
                401, f"The identity provider would not complete this sign-in ({said})."
            )
        if not isinstance(answer.get("id_token"), str):
            raise _unavailable("its token answer holds no ID token (is openid in oidc.scopes?)")
        return answer

    async def _algorithms(self) -> list[str]:
        offered = (await self.metadata()).get("id_token_signing_alg_values_supported") or ["RS256"]
        algorithms = [a for a in offered if a in ASYMMETRIC_ALGORITHMS]
        if not algorithms:
            raise _unavailable(
                f"it signs ID tokens with {', '.join(map(str, offered))}, none of which is a "
                "published-key algorithm this gateway accepts"
            )
        return algorithms

    async def _decode(self, id_token: str) -> jwt.Token:
        registry = JWSRegistry(algorithms=await self._algorithms())
        try:
            try:
                return jwt.decode(id_token, await self.keys(), registry=registry)
            except InvalidKeyIdError:
                # The provider may have rotated its keys since they were read.
                return jwt.decode(id_token, await self.keys(refresh=True), registry=registry)
        except BadSignatureError as exc:
            raise SignInRefused(
                401,
                "The ID token's signature does not verify with the keys the identity provider "
                "publishes: it was not signed by the provider, or was altered on the way.",
            ) from exc
        except InvalidKeyIdError as exc:
            raise SignInRefused(
                401, "The ID token is signed with a key the identity provider does not publish."
            ) from exc
        except JoseError as exc:
            raise SignInRefused(
                401, f"The ID token cannot be used ({exc.error}: {exc.description})."
            ) from exc

    async def identity(self, answer: Mapping[str, Any], login: LoginState) -> Identity:
        """Who the token answer is about, once its ID token passed every check."""
        token = await self._decode(answer["id_token"])
        options: dict[str, Any] = {
            "iss": {"essential": True, "value": self.issuer},
            "aud": {"essential": True, "value": self.client_id},
            "sub": {"essential": True},
            "exp": {"essential": True},
            "iat": {"essential": True},
            "nonce": {"essential": True, "value": login.nonce},
        }
        params = {
            "nonce": login.nonce,
            "client_id": self.client_id,
            "access_token": answer.get("access_token"),
        }
        claims = CodeIDToken(token.claims, token.header, options, params)
        try:
            claims.validate(now=int(time.time()), leeway=int(self.settings.clock_skew_s))
        except ExpiredTokenError as exc:
            ago = time.time() - float(token.claims.get("exp", 0))
            raise SignInRefused(
                401,
                f"The ID token had expired {ago:.0f} s before it arrived (by this gateway's "
                f"clock, {self.settings.clock_skew_s:g} s allowed): check that this gateway's "
                "and the provider's clocks agree, then sign in again.",
            ) from exc
        except MissingClaimError as exc:
            raise SignInRefused(401, f"The ID token lacks the {exc.claim} claim.") from exc
        except InvalidClaimError as exc:
            raise SignInRefused(401, self._invalid(exc.claim, token.claims)) from exc
        found: dict[str, Any] = dict(token.claims)
        groups = claim_values(found, self.settings.groups_claim)
        if groups is None or not isinstance(found.get("email"), str):
            found = await self._with_userinfo(found, answer)
            groups = claim_values(found, self.settings.groups_claim)
        subject, email, name = found["sub"], found.get("email"), found.get("name")
        if not isinstance(subject, str) or not 0 < len(subject) <= 255:
            raise SignInRefused(401, "The ID token's subject is not 1 to 255 characters.")
        return Identity(
            subject=subject,
            email=email[:320] if isinstance(email, str) else None,
            name=name[:200] if isinstance(name, str) else None,
            groups=tuple(groups or ()),
        )

    def _invalid(self, claim: str, claims: Mapping[str, Any]) -> str:
        if claim == "aud":
            return (
                f"The ID token is meant for {claims.get('aud')!r}, not for this gateway "
                f"(oidc.client_id {self.client_id!r})."
            )
        if claim == "iss":
            return f"The ID token was issued by {claims.get('iss')!r}, not by {self.issuer!r}."
        if claim == "nonce":
            return (
                "The ID token does not answer this browser's sign-in (its nonce differs): "
                "start again."
            )
        if claim == "azp":
            return f"The ID token was issued to {claims.get('azp')!r}, not to this gateway."
        if claim in ("iat", "nbf"):
            return (
                "The ID token is dated in the future: check that this gateway's and the "
                "provider's clocks agree."
            )
        return f"The ID token's {claim} claim is not valid."

    async def _with_userinfo(
        self, claims: dict[str, Any], answer: Mapping[str, Any]
    ) -> dict[str, Any]:
        """The ID token's claims completed by the UserInfo endpoint's (where the groups or
        the email are not in the ID token, as the specification has it by default)."""
        endpoint = (await self.metadata()).get("userinfo_endpoint")
        access = answer.get("access_token")
        if not isinstance(endpoint, str) or not isinstance(access, str):
            return claims
        info = await self._get_json(endpoint, headers={"Authorization": f"Bearer {access}"})
        if info.get("sub") != claims["sub"]:
            raise SignInRefused(
                401, "The identity provider's UserInfo answer is about another person."
            )
        return {**info, **claims}
