// REST client for /api. Every failure becomes an ApiError with a readable message
// (the backend's {"detail": ...}, or a sentence for network errors) so pages can show it.

export class ApiError extends Error {
  constructor(status, message, body = null) {
    super(message);
    this.name = "ApiError";
    this.status = status;
    this.body = body;
  }
}

const STATUS_HINT = {
  401: "You are not logged in (or your session expired).",
  403: "Your role is not allowed to do this.",
  404: "Not found.",
  409: "Someone else changed this in the meantime.",
  413: "The upload is too large.",
  422: "The input was not accepted.",
  429: "Too many attempts; wait a moment and retry.",
};

/** Turn a FastAPI error body into one readable sentence. */
export function readableDetail(status, body, statusText = "") {
  let detail = body && body.detail !== undefined ? body.detail : null;
  if (Array.isArray(detail)) {
    // pydantic validation errors: [{loc: [...], msg: "..."}]
    detail = detail
      .map((d) => {
        const loc = Array.isArray(d.loc) ? d.loc.filter((p) => p !== "body").join(".") : "";
        return loc ? `${loc}: ${d.msg}` : d.msg;
      })
      .join("; ");
  } else if (detail && typeof detail === "object") {
    detail = detail.message || JSON.stringify(detail);
  }
  const hint = STATUS_HINT[status] || `The server answered ${status} ${statusText}.`;
  if (!detail) return hint;
  return status >= 500 ? `Server error (${status}): ${detail}` : String(detail);
}

// Idempotent actions (docs/provenance.md): every POST carries an Idempotency-Key; an identical
// POST sent while the first is still pending reuses its key (the server then returns the same
// job), and the button that started a request stays disabled until it settles.
const pendingKeys = new Map();

function newKey() {
  return globalThis.crypto?.randomUUID ? crypto.randomUUID()
    : `${Date.now().toString(36)}-${Math.random().toString(36).slice(2)}`;
}

async function send(method, path, opts = {}) {
  if (method === "GET" || method === "HEAD") return sendOnce(method, path, opts);
  const active = globalThis.document?.activeElement;
  const button = active && active.tagName === "BUTTON" && !active.disabled ? active : null;
  const sig = method === "POST" && opts.json !== undefined ? `${path} ${JSON.stringify(opts.json)}` : null;
  let key = null;
  if (sig !== null) {
    key = pendingKeys.get(sig) || newKey();
    pendingKeys.set(sig, key);
  }
  if (button) button.disabled = true;
  try {
    const headers = key ? { "Idempotency-Key": key, ...(opts.headers || {}) } : opts.headers;
    return await sendOnce(method, path, { ...opts, headers });
  } finally {
    if (sig !== null) pendingKeys.delete(sig);
    if (button) button.disabled = false;
  }
}

/** How long a request may wait for the server's answer (its status and headers) before it
 * is given up with a readable error: a GET 60 s, a request carrying data (a 20 MP mask on a
 * slow uplink) 180 s; a page passes `timeoutMs` where it knows better. */
export const DEFAULT_TIMEOUT_MS = 60_000;
const UPLOAD_TIMEOUT_MS = 180_000;

/** True for the error of a request cancelled by its caller's AbortSignal (a superseded load):
 * pages drop it silently instead of showing it. */
export function isAbort(e) {
  return !!e && (e.name === "AbortError" || (e instanceof ApiError && e.aborted));
}

async function sendOnce(method, path, { json, body, headers = {}, keepalive = false, signal = null, timeoutMs = method === "GET" || method === "HEAD" ? DEFAULT_TIMEOUT_MS : UPLOAD_TIMEOUT_MS } = {}) {
  // one controller per request: aborted by the caller's signal (the body download too: the
  // response's stream is bound to it) or by the timeout while waiting for the answer
  const ctl = new AbortController();
  let timedOut = false;
  const onAbort = () => ctl.abort();
  if (signal) {
    if (signal.aborted) ctl.abort();
    else signal.addEventListener("abort", onAbort, { once: true });
  }
  const timer = timeoutMs > 0 ? setTimeout(() => { timedOut = true; ctl.abort(); }, timeoutMs) : null;
  const init = { method, headers: { ...headers }, credentials: "same-origin", keepalive, signal: ctl.signal };
  if (json !== undefined) {
    init.body = JSON.stringify(json);
    init.headers["Content-Type"] = "application/json";
  } else if (body !== undefined) {
    init.body = body;
  }
  let res;
  try {
    res = await fetch(path.startsWith("/") ? `/api${path}` : path, init);
  } catch (e) {
    if (timedOut) throw new ApiError(0, `The server did not answer ${method} ${path} within ${Math.round(timeoutMs / 1000)} s. Check the connection and retry.`);
    if (ctl.signal.aborted) {
      const err = new ApiError(0, `${method} ${path} was cancelled.`);
      err.aborted = true;
      throw err;
    }
    throw new ApiError(0, `Cannot reach the server (${e.message}). Check the connection and retry.`);
  } finally {
    if (timer !== null) clearTimeout(timer);
  }
  if (!res.ok) {
    let parsed = null;
    try {
      parsed = await res.json();
    } catch {
      parsed = null;
    }
    throw new ApiError(res.status, readableDetail(res.status, parsed, res.statusText), parsed);
  }
  return res;
}

async function asJson(res) {
  if (res.status === 204) return null;
  const text = await readBody(res, "text");
  return text ? JSON.parse(text) : null;
}

/** Read a body; a cancelled download (the caller's signal) becomes an aborted ApiError. */
async function readBody(res, how) {
  try {
    return await res[how]();
  } catch (e) {
    if (e && e.name === "AbortError") {
      const err = new ApiError(0, `The download of ${res.url} was cancelled.`);
      err.aborted = true;
      throw err;
    }
    throw e;
  }
}

export const api = {
  send,
  /** opts: {signal} cancels the request and its download; {timeoutMs} the wait for an answer. */
  async get(path, opts = {}) {
    return asJson(await send("GET", path, opts));
  },
  async post(path, json) {
    return asJson(await send("POST", path, { json: json ?? {} }));
  },
  async patch(path, json) {
    return asJson(await send("PATCH", path, { json }));
  },
  async put(path, json) {
    return asJson(await send("PUT", path, { json }));
  },
  /** GET a binary resource; returns {blob, etag, number, prefillId} or null on 404 / 204. */
  async blob(path, { allow404 = true, signal = null, timeoutMs } = {}) {
    try {
      const res = await send("GET", path, { signal, ...(timeoutMs !== undefined ? { timeoutMs } : {}) });
      if (res.status === 204) return null;
      const n = res.headers.get("X-Mask-Number");
      return { blob: await readBody(res, "blob"), etag: parseEtag(res.headers.get("ETag")), number: n ? Number(n) : null, prefillId: res.headers.get("X-Prefill-Id") };
    } catch (e) {
      if (allow404 && e instanceof ApiError && e.status === 404) return null;
      throw e;
    }
  },
};

/** 'W/"12"' -> '12' */
export function parseEtag(v) {
  if (!v) return null;
  return v.replace(/^W\//, "").replace(/^"(.*)"$/, "$1");
}
