// The oxbow search page. Uses only the public HTTP API (/v1/...), so it doubles as an example of it:
//   POST /v1/search                     search with an uploaded photo (bbox, top_k)
//   GET  /v1/images/{id}/similar        search with an indexed image
//   GET  /v1/images/{id}/thumbnail      result and collection thumbnails
//   POST /v1/match?correspondences=true the match view's lines (query photo vs the result's thumbnail)
//   GET/POST/DELETE /v1/images          the collection; GET /v1/stats the status strip
//   GET  /v1/collections                the collection picker: with a collection other than "default"
//                                       chosen, the routes above (not /v1/match) are those of
//                                       /v1/collections/{name}/... (see v1() below)
// No framework, no build step, no network access beyond this server.

const $ = (id) => document.getElementById(id);
const SVG_NS = 'http://www.w3.org/2000/svg';
const PAGE_SIZE = 24;
const MATCH_THUMBNAIL_PX = 512;  // the largest thumbnail the server keeps
const MAX_LINES = 150;           // correspondence lines drawn in the match view at most
const DEFAULT_COLLECTION = 'default';  // the collection of the routes without /v1/collections/{name}

const state = {
  query: null,        // {kind: 'file', file, url, width, height} | {kind: 'id', id, url, width, height}
  box: null,          // [x1, y1, x2, y2] in query pixels, or null
  lastResponse: null, // the last search response
  offset: 0,          // collection page
  collection: sessionStorage.getItem('oxbow-collection') || '',  // '' until the server lists its collections
  collections: [],    // the names GET /v1/collections listed (none from a server without collections)
};

// ---- API ---------------------------------------------------------------------------------------

class ApiError extends Error {
  constructor(status, code, message, requestId) {
    super(message);
    this.status = status;
    this.code = code;
    this.requestId = requestId;
  }
}

function apiKey() { return sessionStorage.getItem('oxbow-api-key') || ''; }

// The path of an image, search or stats route ('/search', '/images/ID/thumbnail?size=256', ...) in the
// chosen collection: /v1/collections/{name}/... for a collection other than "default", else /v1/...
// Every such request of the page takes its path from here.
function v1(route) {
  const name = state.collection;
  return name && name !== DEFAULT_COLLECTION ? `/v1/collections/${encodeURIComponent(name)}${route}` : `/v1${route}`;
}

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  if (apiKey()) headers.set('X-API-Key', apiKey());
  let response;
  try {
    response = await fetch(path, { ...options, headers });
  } catch (e) {
    throw new ApiError(0, 'network', 'cannot reach the server (' + e.message + ')', '');
  }
  if (response.ok) return response;
  let code = 'http_' + response.status;
  let message = response.statusText;
  let requestId = response.headers.get('X-Request-Id') || '';
  try {
    const body = await response.json();
    if (body && body.error) {
      code = body.error.code || code;
      message = body.error.message || message;
      requestId = body.error.request_id || requestId;
    }
  } catch (_) { /* not JSON: keep the status text */ }
  throw new ApiError(response.status, code, message, requestId);
}

async function apiJson(path, options) { return (await api(path, options)).json(); }

// What an API error means to the person using the page; the server's own message follows.
function explain(error) {
  if (!(error instanceof ApiError)) return 'Unexpected error: ' + error.message;
  const lead = {
    invalid_image: 'The file is not a readable image (it may be truncated or damaged).',
    image_too_large: 'The image is too large for this server.',
    payload_too_large: 'The file is too large to upload to this server.',
    unsupported_format: 'This kind of file is not supported.',
    unauthenticated: 'This server needs an API key for that.',
    permission_denied: 'The API key was refused.',
    unavailable: 'The server is busy or still loading its index; try again in a moment.',
    resource_exhausted: 'The server is busy; try again in a moment.',
    not_found: 'Not found.',
    collection_full: 'The collection is full.',
    already_exists: 'An image with this id is already in the collection.',
    invalid_argument: 'The request was not valid.',
    incompatible: 'The request does not fit this index.',
    network: 'The server cannot be reached.',
  }[error.code] || (error.status >= 500 ? 'The server failed to answer.' : 'The request failed.');
  const status = error.status ? ` (HTTP ${error.status} ${error.code})` : '';
  return `${lead} ${error.message}${status}`;
}

// ---- Messages and status -----------------------------------------------------------------------

function showError(error) {
  const box = $('messages');
  box.replaceChildren();
  const p = document.createElement('p');
  p.className = 'error';
  p.textContent = 'Error: ' + explain(error);
  box.append(p);
}

function showInfo(text) {
  const box = $('messages');
  box.replaceChildren();
  if (!text) return;
  const p = document.createElement('p');
  p.className = 'info';
  p.textContent = text;
  box.append(p);
}

function formatUptime(seconds) {
  const s = Math.floor(seconds);
  if (s < 120) return `${s} s`;
  if (s < 7200) return `${Math.floor(s / 60)} min`;
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}

function formatTimings(t) {
  const parts = [];
  for (const [name, label] of [['decode_extract', 'extract'], ['quantize', 'quantize'], ['score', 'score'],
                               ['verify', 'verify'], ['qe', 'expand']]) {
    if (t[name] !== undefined && (t[name] > 0 || name !== 'decode_extract')) parts.push(`${label} ${t[name].toFixed(0)}`);
  }
  return `${parts.join(', ')}; total ${t.total.toFixed(0)} ms`;
}

async function refreshStatus() {
  const el = $('status');
  let text;
  try {
    const s = await apiJson(v1('/stats'));
    text = `${s.images.toLocaleString()} images · ${s.features.toLocaleString()} features · ` +
           `${s.words.toLocaleString()} words · up ${formatUptime(s.uptime_s)}`;
  } catch (e) {
    text = e.status === 503 ? 'Index loading…' : 'Server unreachable';
  }
  if (state.lastResponse) text += ` · last search: ${formatTimings(state.lastResponse.timings_ms)}`;
  el.textContent = text;
}

// ---- Small DOM helpers -------------------------------------------------------------------------

function svgElement(name, attributes) {
  const el = document.createElementNS(SVG_NS, name);
  for (const [k, v] of Object.entries(attributes || {})) el.setAttribute(k, String(v));
  return el;
}

function thumbnailUrl(id, size) {
  return v1(`/images/${encodeURIComponent(id)}/thumbnail?size=${size}`);
}

// A picture with an SVG overlay in the image's own pixel coordinates (viewBox 0 0 width height).
function framedPicture(src, alt, width, height) {
  const frame = document.createElement('div');
  frame.className = 'frame';
  frame.style.aspectRatio = `${width} / ${height}`;
  const img = document.createElement('img');
  img.src = src;
  img.alt = alt;
  img.loading = 'lazy';
  img.decoding = 'async';
  const overlay = svgElement('svg', { class: 'overlay', viewBox: `0 0 ${width} ${height}`,
                                      preserveAspectRatio: 'none', 'aria-hidden': 'true' });
  frame.append(img, overlay);
  return { frame, img, overlay };
}

function boxRect(box, className, strokeScale) {
  const rect = svgElement('rect', { x: box[0], y: box[1], width: box[2] - box[0], height: box[3] - box[1],
                                    class: className });
  rect.style.strokeWidth = String(strokeScale);
  return rect;
}

function fmt(x) { return Number(x).toFixed(1); }

// ---- Search ------------------------------------------------------------------------------------

function topK() {
  const k = parseInt($('top-k').value, 10);
  return Number.isFinite(k) && k >= 1 && k <= 100 ? k : 20;
}

async function setQueryFile(file) {
  if (!file) return;
  if (state.query && state.query.url && state.query.kind === 'file') URL.revokeObjectURL(state.query.url);
  state.query = { kind: 'file', file, url: URL.createObjectURL(file), width: 0, height: 0 };
  state.box = null;
  await showQuery();
  await runSearch();
}

async function setQueryId(id) {
  let record;
  try {
    record = await apiJson(v1(`/images/${encodeURIComponent(id)}`));
  } catch (e) {
    showError(e);
    return;
  }
  state.query = { kind: 'id', id, url: thumbnailUrl(id, MATCH_THUMBNAIL_PX), width: record.width, height: record.height };
  state.box = null;
  await showQuery();
  await runSearch();
}

async function showQuery() {
  const img = $('query-image');
  $('query-panel').hidden = false;
  img.src = state.query.url;
  try {
    await img.decode();
  } catch (_) {
    // A file the browser cannot show may still be one the server reads (or not: the search says).
  }
  if (!state.query.width) {
    state.query.width = img.naturalWidth || 1;
    state.query.height = img.naturalHeight || 1;
  }
  const overlay = $('query-overlay');
  overlay.setAttribute('viewBox', `0 0 ${state.query.width} ${state.query.height}`);
  overlay.setAttribute('preserveAspectRatio', 'none');
  $('query-frame').style.aspectRatio = `${state.query.width} / ${state.query.height}`;
  drawQueryBox();
}

async function runSearch() {
  if (!state.query) return;
  closeMatchView();
  const params = new URLSearchParams({ top_k: String(topK()) });
  if (state.box) params.set('bbox', state.box.map((v) => v.toFixed(1)).join(','));
  $('results-summary').textContent = 'Searching…';
  $('results').setAttribute('aria-busy', 'true');
  let response;
  try {
    if (state.query.kind === 'file') {
      const form = new FormData();
      form.append('file', state.query.file, state.query.file.name);
      response = await apiJson(v1(`/search?${params}`), { method: 'POST', body: form });
      // The server's size is authoritative (EXIF orientation, formats the browser cannot show).
      state.query.width = response.query.width;
      state.query.height = response.query.height;
      $('query-overlay').setAttribute('viewBox', `0 0 ${state.query.width} ${state.query.height}`);
      $('query-frame').style.aspectRatio = `${state.query.width} / ${state.query.height}`;
    } else {
      response = await apiJson(v1(`/images/${encodeURIComponent(state.query.id)}/similar?${params}`));
    }
  } catch (e) {
    $('results').removeAttribute('aria-busy');
    $('results').replaceChildren();
    $('results-summary').textContent = 'No results: the search failed (see the message above).';
    showError(e);
    return;
  }
  showInfo('');
  state.lastResponse = response;
  renderResults(response);
  refreshStatus();
}

function renderResults(response) {
  const list = $('results');
  list.removeAttribute('aria-busy');
  list.replaceChildren();
  const verified = response.results.filter((r) => r.verified).length;
  const q = response.query;
  $('results-summary').textContent =
    `${response.results.length} results, ${verified} verified, from ${response.candidates} candidates; ` +
    `query ${q.width} × ${q.height} px, ${q.features_used} of ${q.features} features used` +
    (q.bbox ? ` (box ${q.bbox.map(fmt).join(', ')})` : '') + `; ${formatTimings(response.timings_ms)}.`;
  for (const r of response.results) {
    const li = document.createElement('li');
    li.className = 'card result' + (r.verified ? ' verified' : '');
    li.dataset.id = r.id;
    li.dataset.rank = r.rank;
    const button = document.createElement('button');
    button.type = 'button';
    button.className = 'card-button';
    button.setAttribute('aria-label', `Rank ${r.rank}: ${r.id}. Show the match with the query.`);
    const { frame, overlay } = framedPicture(thumbnailUrl(r.id, 256), `Result ${r.rank}: ${r.id}`, r.width, r.height);
    if (r.region) {
      overlay.append(boxRect(r.region, 'region', Math.max(r.width, r.height) / 100));
      frame.classList.add('has-region');
    }
    const caption = document.createElement('div');
    caption.className = 'caption';
    const title = document.createElement('strong');
    title.textContent = `#${r.rank} ${r.id}`;
    const facts = document.createElement('span');
    facts.textContent = `score ${r.score.toFixed(3)} · ` +
      (!r.verified ? `not verified (${r.inliers} inliers)`
        : r.via ? `✓ verified via ${r.via}, ${r.inliers} inliers` : `✓ verified, ${r.inliers} inliers`);
    caption.append(title, facts);
    button.append(frame, caption);
    button.addEventListener('click', () => openMatchView(r));
    li.append(button);
    list.append(li);
  }
}

// ---- The query box (mouse, touch, keyboard) ----------------------------------------------------

function drawQueryBox() {
  const rect = $('query-box');
  const has = state.box !== null;
  rect.setAttribute('visibility', has ? 'visible' : 'hidden');
  $('search-box-button').disabled = !has;
  $('clear-box-button').disabled = !has;
  if (!has) {
    $('box-text').textContent = 'No box: the whole photo is searched.';
    return;
  }
  const [x1, y1, x2, y2] = state.box;
  rect.setAttribute('x', x1);
  rect.setAttribute('y', y1);
  rect.setAttribute('width', x2 - x1);
  rect.setAttribute('height', y2 - y1);
  rect.style.strokeWidth = String(Math.max(state.query.width, state.query.height) / 150);
  $('box-text').textContent = `Box: x ${fmt(x1)} to ${fmt(x2)}, y ${fmt(y1)} to ${fmt(y2)} (query pixels).`;
}

function clampBox(box) {
  const w = state.query.width;
  const h = state.query.height;
  let [x1, y1, x2, y2] = box;
  x1 = Math.max(0, Math.min(x1, w - 2));
  y1 = Math.max(0, Math.min(y1, h - 2));
  x2 = Math.max(x1 + 2, Math.min(x2, w));
  y2 = Math.max(y1 + 2, Math.min(y2, h));
  return [x1, y1, x2, y2];
}

function pointerToImage(event) {
  const overlay = $('query-overlay');
  const r = overlay.getBoundingClientRect();
  return [(event.clientX - r.left) / r.width * state.query.width, (event.clientY - r.top) / r.height * state.query.height];
}

function setUpQueryBox() {
  const overlay = $('query-overlay');
  let start = null;
  overlay.addEventListener('pointerdown', (event) => {
    if (!state.query) return;
    event.preventDefault();
    overlay.setPointerCapture(event.pointerId);
    overlay.focus();
    start = pointerToImage(event);
  });
  overlay.addEventListener('pointermove', (event) => {
    if (!start) return;
    const p = pointerToImage(event);
    state.box = clampBox([Math.min(start[0], p[0]), Math.min(start[1], p[1]), Math.max(start[0], p[0]),
                          Math.max(start[1], p[1])]);
    drawQueryBox();
  });
  const finish = () => {
    if (!start) return;
    start = null;
    // A click without a drag leaves a tiny box: treat it as none.
    if (state.box && (state.box[2] - state.box[0] < 8 || state.box[3] - state.box[1] < 8)) state.box = null;
    drawQueryBox();
  };
  overlay.addEventListener('pointerup', finish);
  overlay.addEventListener('pointercancel', finish);
  overlay.addEventListener('keydown', (event) => {
    if (!state.query) return;
    const step = Math.max(state.query.width, state.query.height) / 50;
    const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (event.key in moves) {
      event.preventDefault();
      if (!state.box) {
        const w = state.query.width;
        const h = state.query.height;
        state.box = [w / 4, h / 4, (3 * w) / 4, (3 * h) / 4];
      } else {
        const [dx, dy] = moves[event.key];
        const b = state.box;
        state.box = event.shiftKey ? clampBox([b[0], b[1], b[2] + dx, b[3] + dy])
                                   : clampBox([b[0] + dx, b[1] + dy, b[2] + dx, b[3] + dy]);
      }
      drawQueryBox();
    } else if (event.key === 'Enter') {
      event.preventDefault();
      runSearch();
    } else if (event.key === 'Escape' || event.key === 'Delete' || event.key === 'Backspace') {
      event.preventDefault();
      state.box = null;
      drawQueryBox();
    }
  });
  $('search-box-button').addEventListener('click', () => runSearch());
  $('clear-box-button').addEventListener('click', () => {
    state.box = null;
    drawQueryBox();
    runSearch();
  });
}

// ---- Match view --------------------------------------------------------------------------------

function closeMatchView() {
  $('match-view').hidden = true;
  $('match-svg').replaceChildren();
}

async function queryBlob() {
  if (state.query.kind === 'file') return state.query.file;
  return (await api(state.query.url)).blob();
}

function transformText(t) {
  const [[a11, a12, tx], [a21, a22, ty]] = t;
  const scale = Math.sqrt(Math.abs(a11 * a22 - a12 * a21));
  const angle = (Math.atan2(a21, a11) * 180) / Math.PI;
  return { matrix: `[[${a11.toFixed(3)}, ${a12.toFixed(3)}, ${tx.toFixed(1)}], [${a21.toFixed(3)}, ${a22.toFixed(3)}, ${ty.toFixed(1)}]]`,
           summary: `scale ${scale.toFixed(2)}, rotation ${angle.toFixed(1)}°, shift (${tx.toFixed(0)}, ${ty.toFixed(0)}) px` };
}

async function openMatchView(result) {
  const view = $('match-view');
  const svg = $('match-svg');
  view.hidden = false;
  svg.replaceChildren();
  $('match-details').replaceChildren();
  $('match-heading').textContent = `Match: query ↔ #${result.rank} ${result.id}`;
  $('match-summary').textContent = 'Matching the query with this image…';
  $('match-heading').focus();
  let thumbBlob;
  let match;
  try {
    thumbBlob = await (await api(thumbnailUrl(result.id, MATCH_THUMBNAIL_PX))).blob();
    const form = new FormData();
    form.append('a', await queryBlob(), 'query');
    form.append('b', thumbBlob, `${result.id}.jpg`);
    match = await apiJson('/v1/match?correspondences=true', { method: 'POST', body: form });
  } catch (e) {
    $('match-summary').textContent = 'The match could not be computed (see the message above).';
    showError(e);
    return;
  }
  // Layout: query on the left, result on the right, both scaled to the same height H (SVG units).
  const H = 400;
  const gap = 16;
  const q = state.query;
  const sq = H / q.height;            // query pixels -> SVG units (the box)
  const sa = H / match.a.height;      // pixels of the image matched as a (the file, or the query's thumbnail)
  const sb = H / match.b.height;      // thumbnail pixels -> SVG units
  const wa = q.width * sq;
  const wb = match.b.width * sb;
  svg.setAttribute('viewBox', `0 0 ${wa + gap + wb} ${H}`);
  const thumbUrl = URL.createObjectURL(thumbBlob);
  svg.append(svgElement('image', { href: q.url, x: 0, y: 0, width: wa, height: H, preserveAspectRatio: 'none' }),
             svgElement('image', { href: thumbUrl, x: wa + gap, y: 0, width: wb, height: H, preserveAspectRatio: 'none' }));
  const ka = q.height / match.a.height;  // a pixels -> query pixels (1 for an uploaded file)
  const inBox = (c) => !state.box || (c[0] * ka >= state.box[0] && c[0] * ka <= state.box[2] &&
                                      c[1] * ka >= state.box[1] && c[1] * ka <= state.box[3]);
  const pairs = (match.correspondences || []).filter(inBox);
  // Hundreds of lines hide the pictures: draw an even sample of at most MAX_LINES.
  const step = Math.max(1, pairs.length / MAX_LINES);
  const drawn = [];
  for (let i = 0; i < pairs.length && drawn.length < MAX_LINES; i += step) drawn.push(pairs[Math.floor(i)]);
  const lines = svgElement('g', { class: 'correspondences' });
  for (const c of drawn) {
    const x1 = c[0] * sa;
    const y1 = c[1] * sa;
    const x2 = wa + gap + c[2] * sb;
    const y2 = c[3] * sb;
    lines.append(svgElement('line', { x1, y1, x2, y2, class: 'corr' }),
                 svgElement('circle', { cx: x1, cy: y1, r: 3, class: 'corr-end' }),
                 svgElement('circle', { cx: x2, cy: y2, r: 3, class: 'corr-end' }));
  }
  if (state.box) {
    const b = state.box.map((v) => v * sq);
    svg.append(svgElement('rect', { x: b[0], y: b[1], width: b[2] - b[0], height: b[3] - b[1], class: 'box' }));
  }
  if (result.region) {
    const s = H / result.height;  // db pixels -> SVG units
    const r = result.region;
    svg.append(svgElement('rect', { x: wa + gap + r[0] * s, y: r[1] * s, width: (r[2] - r[0]) * s,
                                    height: (r[3] - r[1]) * s, class: 'region' }));
  }
  svg.append(lines);
  $('match-summary').textContent =
    (drawn.length < pairs.length ? `${drawn.length} of ${pairs.length}` : `${pairs.length}`) +
    ` verified correspondences drawn as lines (query photo against the result's ` +
    `${match.b.width} × ${match.b.height} px thumbnail; model ${match.model}, ${match.inliers} inliers of ` +
    `${match.tentative_matches} tentative matches).`;
  const details = $('match-details');
  const dl = document.createElement('dl');
  const add = (term, value) => {
    const dt = document.createElement('dt');
    dt.textContent = term;
    const dd = document.createElement('dd');
    dd.textContent = value;
    dl.append(dt, dd);
  };
  add('Search result', `rank ${result.rank}, score ${result.score.toFixed(3)}, ` +
      (result.verified ? `verified with ${result.inliers} inliers` : 'not verified'));
  if (result.verified) {
    const t = transformText(result.transform);
    add('Transform (result ← query pixels)', t.matrix);
    add('In words', t.summary);
    add('Matched region in the result', result.region.map(fmt).join(', '));
  }
  add('Result image', `${result.width} × ${result.height} px`);
  details.replaceChildren(dl);
}

// ---- Collection --------------------------------------------------------------------------------

async function withApiKey(action) {
  for (let attempt = 0; attempt < 3; attempt++) {
    try {
      return await action();
    } catch (e) {
      if (!(e instanceof ApiError) || (e.status !== 401 && e.status !== 403)) throw e;
      const ok = await askForKey(e.status === 403 ? 'The API key was refused; enter the right one.'
                                                  : 'This server needs an API key to add or delete images.');
      if (!ok) throw e;
    }
  }
  return action();
}

// Asks for the API key; resolves true when one was given. With allowEmpty an empty key is taken too (it
// forgets the key). A new key may read other collections: the picker's list is read again.
function askForKey(reason, allowEmpty = false) {
  const dialog = $('key-dialog');
  $('key-heading').textContent = allowEmpty ? 'API key' : 'API key needed';
  $('key-reason').textContent = reason;
  $('key-input').value = apiKey();
  return new Promise((resolve) => {
    dialog.addEventListener('close', () => {
      const key = $('key-input').value;
      const ok = dialog.returnValue === 'ok' && (key !== '' || allowEmpty);
      const changed = ok && key !== apiKey();
      if (ok && key) sessionStorage.setItem('oxbow-api-key', key);
      else if (ok) sessionStorage.removeItem('oxbow-api-key');
      if (changed) loadCollections().then(refreshStatus);
      resolve(ok);
    }, { once: true });
    dialog.showModal();
    $('key-input').focus();
  });
}

async function loadCollection() {
  let page;
  try {
    page = await apiJson(v1(`/images?offset=${state.offset}&limit=${PAGE_SIZE}`));
  } catch (e) {
    showError(e);
    return;
  }
  const list = $('collection');
  list.replaceChildren();
  const last = Math.min(page.total, state.offset + page.images.length);
  $('browse-summary').textContent = page.total === 0 ? 'The collection is empty.'
    : `Images ${state.offset + 1} to ${last} of ${page.total}, by id.`;
  $('prev-page').disabled = state.offset === 0;
  $('next-page').disabled = last >= page.total;
  for (const image of page.images) {
    const li = document.createElement('li');
    li.className = 'card';
    li.dataset.id = image.id;
    const { frame } = framedPicture(thumbnailUrl(image.id, 256), `Image ${image.id}`, image.width, image.height);
    const caption = document.createElement('div');
    caption.className = 'caption';
    const title = document.createElement('strong');
    title.textContent = image.id;
    const facts = document.createElement('span');
    facts.textContent = `${image.width} × ${image.height} px · ${image.features} features`;
    const origin = document.createElement('span');
    origin.className = 'origin';
    origin.textContent = `${image.source || 'no source'} · added ${new Date(image.added_unix_ms).toLocaleString()}`;
    caption.append(title, facts, origin);
    if (image.metadata !== null) {
      const meta = document.createElement('code');
      meta.textContent = JSON.stringify(image.metadata);
      caption.append(meta);
    }
    const actions = document.createElement('div');
    actions.className = 'row';
    const search = document.createElement('button');
    search.type = 'button';
    search.textContent = 'Search with it';
    search.setAttribute('aria-label', `Search with ${image.id}`);
    search.addEventListener('click', () => { showSection('search'); setQueryId(image.id); });
    const remove = document.createElement('button');
    remove.type = 'button';
    remove.className = 'danger';
    remove.textContent = 'Delete';
    remove.setAttribute('aria-label', `Delete ${image.id}`);
    remove.addEventListener('click', () => deleteImage(image.id));
    actions.append(search, remove);
    li.append(frame, caption, actions);
    list.append(li);
  }
}

async function deleteImage(id) {
  if (!window.confirm(`Delete ${id} from the collection?`)) return;
  const path = v1(`/images/${encodeURIComponent(id)}`);  // this collection's, whatever a new key lists
  try {
    await withApiKey(() => api(path, { method: 'DELETE' }));
  } catch (e) {
    showError(e);
    return;
  }
  await loadCollection();
  showInfo(`Deleted ${id}.`);
  refreshStatus();
}

async function addImage(event) {
  event.preventDefault();
  const file = $('add-file').files[0];
  const id = $('add-id').value.trim();
  if (!file || !id) return;
  const form = new FormData();
  form.append('id', id);
  const metadata = $('add-metadata').value.trim();
  if (metadata) form.append('metadata', metadata);
  form.append('file', file, file.name);
  $('add-button').disabled = true;
  const path = v1('/images');  // this collection's, whatever a new key lists
  try {
    const added = await withApiKey(async () => apiJson(path, { method: 'POST', body: form }));
    showInfo(`Added ${added.id}: ${added.width} × ${added.height} px, ${added.features} features.`);
    $('add-form').reset();
  } catch (e) {
    showError(e);
  } finally {
    $('add-button').disabled = false;
  }
  await loadCollection();
  refreshStatus();
}

// ---- Collections -------------------------------------------------------------------------------

// Reads the collections the key may read and shows them in the picker; a server without collections
// (GET /v1/collections answers 404), or one that lists none, leaves it hidden and the page on /v1/...
async function loadCollections() {
  let names = [];
  try {
    const answer = await apiJson('/v1/collections');
    names = (answer.collections || []).map((c) => c.name).filter((n) => typeof n === 'string');
  } catch (_) {
    names = [];  // 404 from an older server; a refused key or no answer: nothing to choose from
  }
  state.collections = names;
  const select = $('collection-select');
  select.replaceChildren(...names.map((name) => {
    const option = document.createElement('option');
    option.value = name;
    option.textContent = name;
    return option;
  }));
  $('collection-picker').hidden = names.length === 0;
  // The remembered choice while it is listed, else "default", else the first listed.
  const chosen = names.length === 0 ? ''
    : names.includes(state.collection) ? state.collection
      : names.includes(DEFAULT_COLLECTION) ? DEFAULT_COLLECTION : names[0];
  if (chosen) select.value = chosen;
  if (chosen !== state.collection) chooseCollection(chosen, names.length > 0);
}

// Makes `name` the collection of every image and search request ('' = the routes without a prefix).
// Results, a query by id and the page of images belonged to the previous one: they go; a query photo
// stays and is searched again in the new collection.
function chooseCollection(name, remember = true) {
  if (remember) sessionStorage.setItem('oxbow-collection', name);
  if (name === state.collection) return;
  state.collection = name;
  closeMatchView();
  state.lastResponse = null;
  $('results').replaceChildren();
  $('results-summary').textContent = 'Choose a photo to search the collection.';
  if (state.query && state.query.kind === 'id') {
    state.query = null;
    state.box = null;
    $('query-panel').hidden = true;
  }
  state.offset = 0;
  if (!$('browse-section').hidden) loadCollection();
  refreshStatus();
  if (state.query) runSearch();
}

// ---- Sections and start-up ---------------------------------------------------------------------

function showSection(name) {
  const search = name === 'search';
  $('search-section').hidden = !search;
  $('browse-section').hidden = search;
  $('tab-search').toggleAttribute('aria-current', search);
  $('tab-browse').toggleAttribute('aria-current', !search);
  if (search) $('tab-search').setAttribute('aria-current', 'page');
  else $('tab-browse').setAttribute('aria-current', 'page');
  if (!search) loadCollection();
}

function setUpDropZone() {
  const zone = $('drop-zone');
  zone.addEventListener('dragover', (event) => {
    event.preventDefault();
    zone.classList.add('dragging');
  });
  zone.addEventListener('dragleave', () => zone.classList.remove('dragging'));
  zone.addEventListener('drop', (event) => {
    event.preventDefault();
    zone.classList.remove('dragging');
    const file = event.dataTransfer.files[0];
    if (file) setQueryFile(file);
  });
  zone.addEventListener('keydown', (event) => {
    if (event.key === 'Enter' || event.key === ' ') {
      event.preventDefault();
      $('query-file').click();
    }
  });
}

async function start() {
  $('query-file').addEventListener('change', (event) => setQueryFile(event.target.files[0]));
  $('search-form').addEventListener('submit', (event) => {
    event.preventDefault();
    const text = $('query-id').value.trim();
    // A pasted address of an indexed image (…/v1/images/ID or …/v1/images/ID/thumbnail) works too, and
    // one of a listed collection's image (…/v1/collections/NAME/images/ID) chooses that collection.
    const m = text.match(/\/v1\/(?:collections\/([^/?#]+)\/)?images\/([^/?#]+)/);
    const id = m ? decodeURIComponent(m[2]) : text;
    const collection = m ? decodeURIComponent(m[1] || DEFAULT_COLLECTION) : '';
    if (collection && state.collections.includes(collection) && collection !== state.collection) {
      $('collection-select').value = collection;
      chooseCollection(collection);
    }
    if (id) setQueryId(id);
  });
  $('match-close').addEventListener('click', () => {
    closeMatchView();
    $('results-heading').scrollIntoView();
  });
  $('tab-search').addEventListener('click', () => showSection('search'));
  $('tab-browse').addEventListener('click', () => showSection('browse'));
  $('prev-page').addEventListener('click', () => { state.offset = Math.max(0, state.offset - PAGE_SIZE); loadCollection(); });
  $('next-page').addEventListener('click', () => { state.offset += PAGE_SIZE; loadCollection(); });
  $('add-form').addEventListener('submit', addImage);
  $('add-file').addEventListener('change', (event) => {
    const file = event.target.files[0];
    if (file && !$('add-id').value) $('add-id').value = file.name.replace(/\.[^.]*$/, '');
  });
  $('collection-select').addEventListener('change', (event) => chooseCollection(event.target.value));
  $('key-button').addEventListener('click', () => askForKey(
    'An API key: the admin key, or a key of a collection (oxk_…). Leave it empty to use none.', true));
  setUpDropZone();
  setUpQueryBox();
  setInterval(refreshStatus, 10000);
  // The requests go to the chosen collection: know the collections before the first one.
  await loadCollections();
  refreshStatus();
  document.body.dataset.ready = 'true';
}

start();
