// A real OpenID Provider (panva/oidc-provider, OpenID Certified) on loopback for eqgw's single
// sign-on tests (tests/test_security_oidc.py starts it as a subprocess).
//
//   node provider.js            listens on a free port of 127.0.0.1 and prints one line of JSON,
//                               {"issuer": "http://127.0.0.1:PORT"}, once it answers.
//
// Environment:
//   OIDC_USERS          JSON {login: {email, name, groups: [...]}}: the accounts; the login page
//                       (oidc-provider's devInteractions) takes any password.
//   OIDC_REDIRECT_URIS  JSON [...]: the redirect URIs every client registers (the gateway's
//                       /auth/oidc/callback).
//   OIDC_CONFORM        "1": claims asked for by scope go to the UserInfo endpoint only, as the
//                       specification has it by default; otherwise they are in the ID token too
//                       (as Keycloak, Entra ID or Okta put a groups claim there).
//
// Clients (secret "eqgw-test-secret", client_secret_basic, PKCE required for all):
//   eqgw              behaves.
//   eqgw-wrong-aud    its ID tokens name another audience ("someone-else").
//   eqgw-expired      its ID tokens expired an hour before they are issued.
//   eqgw-foreign-key  its ID tokens are signed (ES256) with a key other than the one that the
//                     provider's JWKS publishes under the same key id.
// The bad tokens are made by the provider itself and reach the gateway as any token does.

import { generateKeyPairSync } from 'node:crypto';
import http from 'node:http';

import Provider from 'oidc-provider';

const SECRET = 'eqgw-test-secret';
const users = JSON.parse(process.env.OIDC_USERS || '{}');
const redirectUris = JSON.parse(process.env.OIDC_REDIRECT_URIS || '[]');
const conform = process.env.OIDC_CONFORM === '1';

function privateJwk(type, options, kid, alg) {
  const { privateKey } = generateKeyPairSync(type, options);
  return { ...privateKey.export({ format: 'jwk' }), kid, alg, use: 'sig' };
}

function publicOf(jwk) {
  const {
    d, p, q, dp, dq, qi, ...pub
  } = jwk;
  return pub;
}

const rsa = privateJwk('rsa', { modulusLength: 2048 }, 'rsa-1', 'RS256');
const ec = privateJwk('ec', { namedCurve: 'P-256' }, 'ec-1', 'ES256');
// Published under ec-1 instead of the key that signs with it.
const foreign = privateJwk('ec', { namedCurve: 'P-256' }, 'ec-1', 'ES256');

const client = (id, extra = {}) => ({
  client_id: id,
  client_secret: SECRET,
  redirect_uris: redirectUris,
  grant_types: ['authorization_code'],
  response_types: ['code'],
  token_endpoint_auth_method: 'client_secret_basic',
  ...extra,
});

const configuration = {
  clients: [
    client('eqgw'),
    client('eqgw-wrong-aud'),
    client('eqgw-expired'),
    client('eqgw-foreign-key', { id_token_signed_response_alg: 'ES256' }),
  ],
  jwks: { keys: [rsa, ec] },
  cookies: { keys: ['eqgw-test-cookie-key'] },
  claims: {
    openid: ['sub'],
    email: ['email', 'email_verified'],
    profile: ['name'],
    groups: ['groups'],
  },
  conformIdTokenClaims: conform,
  pkce: { required: () => true },
  features: { devInteractions: { enabled: true } },
  async findAccount(ctx, id) {
    const user = users[id];
    if (!user) return undefined;
    return {
      accountId: id,
      async claims() {
        return {
          sub: id,
          email: user.email,
          email_verified: true,
          name: user.name,
          groups: user.groups,
        };
      },
    };
  },
  // A first-party application: no consent page, the sign-in grants what it asks for.
  async loadExistingGrant(ctx) {
    const { oidc } = ctx;
    const grantId = oidc.result?.consent?.grantId || oidc.session.grantIdFor(oidc.client.clientId);
    if (grantId) return oidc.provider.Grant.find(grantId);
    const grant = new oidc.provider.Grant({
      clientId: oidc.client.clientId,
      accountId: oidc.session.accountId,
    });
    grant.addOIDCScope(oidc.params.scope || 'openid');
    await grant.save();
    return grant;
  },
  ttl: {
    AccessToken: 600,
    AuthorizationCode: 60,
    IdToken: 600,
    Interaction: 600,
    Session: 3600,
    Grant: 3600,
  },
};

const server = http.createServer();
server.listen(0, '127.0.0.1', () => {
  const issuer = `http://127.0.0.1:${server.address().port}`;
  const provider = new Provider(issuer, configuration);

  const issue = provider.IdToken.prototype.issue;
  provider.IdToken.prototype.issue = function issueMisbehaving(options = {}) {
    if (options.use === 'idtoken') {
      const id = this.client.clientId;
      if (id === 'eqgw-expired') {
        return issue.call(this, { ...options, expiresAt: Math.floor(Date.now() / 1000) - 3600 });
      }
      if (id === 'eqgw-wrong-aud') {
        const real = this.client;
        this.client = new Proxy(real, {
          get: (target, prop) => (prop === 'clientId' ? 'someone-else' : Reflect.get(target, prop)),
        });
        return issue.call(this, options).finally(() => { this.client = real; });
      }
    }
    return issue.call(this, options);
  };

  provider.use(async (ctx, next) => {
    await next();
    if (ctx.path === '/jwks' && ctx.status === 200) {
      ctx.body = { keys: [publicOf(rsa), publicOf(foreign)] };
    }
  });

  server.on('request', provider.callback());
  process.stdout.write(`${JSON.stringify({ issuer })}\n`);
});

process.on('SIGTERM', () => server.close(() => process.exit(0)));
