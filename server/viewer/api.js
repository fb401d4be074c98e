// The viewer's calls on the REST API (docs/api.md): JSON and binary requests with fetch, uploads
// with XMLHttpRequest (the one browser API that reports upload progress). Every call carries the
// API key the user typed in, when there is one; it is kept in this origin's localStorage.

const KEY_STORAGE = 'c4g-api-key';

/** The API key to send, or '' for none. */
export function apiKey() {
  try {
    return localStorage.getItem(KEY_STORAGE) || '';
  } catch {
    return '';
  }
}

/** Remembers `key` for later visits ('' forgets it). */
export function setApiKey(key) {
  try {
    if (key) localStorage.setItem(KEY_STORAGE, key);
    else localStorage.removeItem(KEY_STORAGE);
  } catch {
    // Storage refused (a private window, say): the key still holds for this page.
  }
  sessionKey = key;
}

let sessionKey = apiKey();

function authHeaders(headers = {}) {
  return sessionKey ? { ...headers, Authorization: `Bearer ${sessionKey}` } : headers;
}

/** A non-2xx answer: the server's `{"error", "kind"}` body, with the status. */
export class ApiError extends Error {
  constructor(status, kind, message, retryAfter) {
    super(message);
    this.status = status;
    this.kind = kind;
    this.retryAfter = retryAfter;
  }
}

async function errorOf(response) {
  let body = {};
  try {
    body = await response.json();
  } catch {
    // Not the service's JSON (a proxy's page, say): the status says enough.
  }
  const retry = Number(response.headers.get('Retry-After'));
  let message = body.error || `${response.status} ${response.statusText}`;
  if (response.status === 401) message = `${message}: enter this server's API key above`;
  return new ApiError(response.status, body.kind, message, Number.isFinite(retry) ? retry : null);
}

async function send(path, init) {
  const response = await fetch(path, { ...init, headers: authHeaders(init.headers) });
  if (!response.ok) throw await errorOf(response);
  return response;
}

/** GET `path` as JSON. */
export async function getJson(path) {
  return (await send(path, { method: 'GET' })).json();
}

/** POST `body` as JSON to `path`; the Response, for the caller to read as it needs. */
export function postJson(path, body, signal) {
  return send(path, {
    method: 'POST',
    headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify(body),
    signal,
  });
}

/** GET `path` as a Blob (an image, say), with the key: an `<img src>` could not send it. */
export async function getBlob(path, signal) {
  return (await send(path, { method: 'GET', signal })).blob();
}

/** Job states after which nothing changes (docs/api.md, Jobs). */
const TERMINAL = new Set(['done', 'failed', 'cancelled']);

/** Whether job `record` has ended. */
export function jobEnded(record) {
  return TERMINAL.has(record.state);
}

/**
 * Calls `onEvent(name, data)` for each server-sent event of GET `path` until the stream ends.
 * Read with fetch, not EventSource: EventSource cannot send the API key. Lines end in `\n` or
 * `\r\n`; a blank line ends an event; `:` lines (keep-alives) are comments.
 */
export async function serverEvents(path, onEvent, signal) {
  const response = await send(path, { method: 'GET', headers: { Accept: 'text/event-stream' }, signal });
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  let name = 'message';
  let data = [];
  for (;;) {
    const { done, value } = await reader.read();
    if (done) return;
    buffer += value;
    let end;
    while ((end = buffer.indexOf('\n')) >= 0) {
      const line = buffer.slice(0, end).replace(/\r$/, '');
      buffer = buffer.slice(end + 1);
      if (line === '') {
        if (data.length) onEvent(name, data.join('\n'));
        [name, data] = ['message', []];
        continue;
      }
      if (line.startsWith(':')) continue;
      const colon = line.indexOf(':');
      const field = colon < 0 ? line : line.slice(0, colon);
      const text = colon < 0 ? '' : line.slice(colon + 1).replace(/^ /, '');
      if (field === 'event') name = text;
      else if (field === 'data') data.push(text);
    }
  }
}

/**
 * Follows job `id` (`GET /v1/jobs/{id}/events`), calling `onRecord(job)` with every record, until
 * it ends; resolves with the last record. A stream that ends before the job does (a draining
 * server ends its streams; the job goes on, perhaps on another replica) is followed again.
 */
export async function followJob(id, onRecord, signal) {
  const path = `/v1/jobs/${encodeURIComponent(id)}/events`;
  let last = null;
  for (;;) {
    try {
      await serverEvents(
        path,
        (name, data) => {
          if (name !== 'job') return;
          last = JSON.parse(data);
          onRecord(last);
        },
        signal,
      );
    } catch (error) {
      // Unreachable or busy for a moment is worth waiting out; a refusal (404: the job is gone)
      // is not.
      const passing = !(error instanceof ApiError) || error.status === 503 || error.status === 429;
      if (signal?.aborted || !passing) throw error;
    }
    if (last && jobEnded(last)) return last;
    await new Promise((resolve) => setTimeout(resolve, 1000));
    if (signal?.aborted) throw new Error('aborted');
  }
}

/**
 * Uploads `files` as one clip: a single video or archive as the body, or image frames (PNG,
 * JPEG) as multipart `frame` parts in name order. `onProgress(sent, total)` follows the bytes;
 * resolves with the clip once the server has encoded it.
 */
export function upload(files, onProgress) {
  const list = [...files];
  let body;
  let contentType = null;
  const images = list.filter((f) => /^image\/(png|jpeg)$/.test(f.type));
  if (list.length > 1 || images.length === 1) {
    if (images.length !== list.length) {
      return Promise.reject(new Error('several files upload as image frames: pick PNG or JPEG frames only'));
    }
    body = new FormData();
    images.sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
    for (const f of images) body.append('frame', f, f.name);
  } else if (list.length === 1) {
    body = list[0];
    contentType = list[0].type || 'application/octet-stream';
  } else {
    return Promise.reject(new Error('no file chosen'));
  }
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('POST', '/v1/clips');
    if (contentType) xhr.setRequestHeader('Content-Type', contentType);
    for (const [name, value] of Object.entries(authHeaders())) xhr.setRequestHeader(name, value);
    xhr.upload.onprogress = (e) => onProgress?.(e.loaded, e.lengthComputable ? e.total : null);
    xhr.onerror = () => reject(new Error('the upload failed: the server is unreachable'));
    xhr.onload = () => {
      let answer = {};
      try {
        answer = JSON.parse(xhr.responseText);
      } catch {
        // Kept empty: the status below says what happened.
      }
      if (xhr.status >= 200 && xhr.status < 300) resolve(answer);
      else reject(new ApiError(xhr.status, answer.kind, answer.error || `upload failed: ${xhr.status}`));
    };
    xhr.send(body);
  });
}
