// Calls to the app's API: every call carries the launch's secret in a header.
//
// The command prints the address once with `?token=...`; the page keeps the token for this
// tab (sessionStorage, so a reload keeps working) and removes it from the address bar.
const TOKEN_KEY = 'semantic3d-token';
const HEADER = 'X-Semantic3D-Token';

function takeToken() {
  const url = new URL(window.location.href);
  const fromAddress = url.searchParams.get('token');
  if (fromAddress) {
    sessionStorage.setItem(TOKEN_KEY, fromAddress);
    url.searchParams.delete('token');
    window.history.replaceState(null, '', url.pathname + url.search + url.hash);
    return fromAddress;
  }
  return sessionStorage.getItem(TOKEN_KEY) || '';
}

const token = takeToken();

export class ApiError extends Error {
  constructor(message, status, data) {
    super(message);
    this.status = status;
    this.data = data;
  }
}

// fetch() with the token header; throws ApiError on an HTTP error.
export async function apiFetch(path, options = {}) {
  const headers = new Headers(options.headers || {});
  headers.set(HEADER, token);
  const response = await fetch(path, { ...options, headers, credentials: 'omit', cache: 'no-store' });
  if (!response.ok) {
    const data = await response.json().catch(() => ({}));
    let detail = typeof data.detail === 'string' ? data.detail : JSON.stringify(data.detail);
    if (response.status === 403 && !token) detail = 'no token: open the address the command printed (it ends with ?token=...)';
    throw new ApiError(detail || response.statusText, response.status, data);
  }
  return response;
}

// JSON GET (no body) or POST (body).
export async function api(path, body) {
  const options = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  };
  const response = await apiFetch(path, options);
  return response.json();
}

// Binary GET.
export async function apiBytes(path) {
  const response = await apiFetch(path);
  return response.arrayBuffer();
}
