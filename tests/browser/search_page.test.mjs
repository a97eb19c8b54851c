// End-to-end test of the search page in a real headless browser (Debian's /usr/bin/chromium driven by
// playwright-core): builds a small index of opencv-doc photos with the oxbow CLI, starts
// `oxbow serve --port 0 --api-key ...`, and drives the page as a person would; then serves a data folder
// of collections (`oxbow serve --data`) and drives the collection picker. Saves screenshots.
//
//   node tests/browser/search_page.test.mjs --oxbow build/server/oxbow --work /tmp/x --artifacts build/test-artifacts/browser
//
// Needs: `npm ci --prefix tests/browser` (playwright-core) and the chromium package; without them it
// fails with a message saying so (it never skips). Exit status 0 when every check passed.
import { spawn, execFileSync } from 'node:child_process';
import fs from 'node:fs';
import path from 'node:path';
import readline from 'node:readline';

const SAMPLES = '/usr/share/doc/opencv-doc/examples/data';
const INDEXED = ['box_in_scene.png', 'graf1.png', 'graf3.png', 'leuvenA.jpg', 'leuvenB.jpg', 'baboon.jpg',
                 'fruits.jpg', 'building.jpg'];
// The second collection of the data folder (step 9): photos of which only box_in_scene is in the first.
const LEUVEN = ['leuvenA.jpg', 'leuvenB.jpg', 'box_in_scene.png'];
const API_KEY = 'browser-test-key';

function parseArgs() {
  const args = { oxbow: '', work: '', artifacts: '', chromium: process.env.CHROMIUM || '/usr/bin/chromium' };
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, '');
    if (!(key in args)) throw new Error(`unknown argument ${argv[i]}`);
    args[key] = argv[i + 1];
  }
  if (!args.oxbow) throw new Error('usage: search_page.test.mjs --oxbow BIN [--work DIR] [--artifacts DIR]');
  if (!args.work) args.work = fs.mkdtempSync('/tmp/oxbow-browser-');
  if (!args.artifacts) args.artifacts = path.join(args.work, 'artifacts');
  return args;
}

let failures = 0;
function check(condition, what) {
  console.log(`${condition ? 'ok  ' : 'FAIL'} ${what}`);
  if (!condition) failures++;
  return condition;
}
function fatal(message) {
  console.error(`search_page.test: ${message}`);
  process.exit(1);
}

// `oxbow serve` over `what` (['--index', DIR] or ['--data', DIR]).
function startServer(oxbow, what, logPath) {
  const log = fs.openSync(logPath, 'a');
  const child = spawn(oxbow, ['serve', ...what, '--port', '0', '--api-key', API_KEY, '--http-workers', '4'],
                      { stdio: ['ignore', 'pipe', log] });
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error('no "listening on" line within 60 s; see ' + logPath)), 60000);
    const lines = readline.createInterface({ input: child.stdout });
    lines.on('line', (line) => {
      const m = line.match(/listening on (http:\/\/\S+)/);
      if (m) {
        clearTimeout(timer);
        resolve({ child, url: m[1] });
      }
    });
    child.on('exit', (code) => reject(new Error(`oxbow serve exited with ${code}; see ${logPath}`)));
  });
}

async function waitReady(url) {
  for (let i = 0; i < 600; i++) {
    try {
      const r = await fetch(url + '/readyz');
      if (r.ok) return;
    } catch (_) { /* not yet */ }
    await new Promise((r) => setTimeout(r, 100));
  }
  throw new Error('the server did not become ready');
}

// A valid PNG header declaring 60000 x 60000 pixels (CRCs included), with one tiny IDAT chunk.
function hugePng() {
  const crcTable = Array.from({ length: 256 }, (_, n) => {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    return c >>> 0;
  });
  const crc = (bytes) => {
    let c = 0xffffffff;
    for (const b of bytes) c = crcTable[(c ^ b) & 0xff] ^ (c >>> 8);
    return (c ^ 0xffffffff) >>> 0;
  };
  const chunk = (type, data) => {
    const body = Buffer.concat([Buffer.from(type, 'ascii'), data]);
    const out = Buffer.alloc(12 + data.length);
    out.writeUInt32BE(data.length, 0);
    body.copy(out, 4);
    out.writeUInt32BE(crc(body), 8 + data.length);
    return out;
  };
  const ihdr = Buffer.alloc(13);
  ihdr.writeUInt32BE(60000, 0);
  ihdr.writeUInt32BE(60000, 4);
  ihdr[8] = 8;  // bit depth
  ihdr[9] = 2;  // RGB
  return Buffer.concat([Buffer.from([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]), chunk('IHDR', ihdr),
                        chunk('IDAT', Buffer.from([0x78, 0x9c, 0x63, 0x00, 0x00, 0x00, 0x01, 0x00, 0x01])),
                        chunk('IEND', Buffer.alloc(0))]);
}

// True when every correspondence line starts in the left picture and ends in the right one (the SVG's
// two <image> elements), i.e. the coordinates were scaled into the right picture.
function linesInTheirPictures(page) {
  return page.$eval('#match-svg', (svg) => {
    const [a, b] = [...svg.querySelectorAll('image')].map((i) => ['x', 'y', 'width', 'height'].map((k) => Number(i.getAttribute(k))));
    const inside = (x, y, r) => x >= r[0] - 0.5 && x <= r[0] + r[2] + 0.5 && y >= r[1] - 0.5 && y <= r[1] + r[3] + 0.5;
    const lines = [...svg.querySelectorAll('line.corr')];
    return lines.length > 0 && lines.every((l) => {
      const v = ['x1', 'y1', 'x2', 'y2'].map((k) => Number(l.getAttribute(k)));
      return inside(v[0], v[1], a) && inside(v[2], v[3], b);
    });
  });
}

async function main() {
  const args = parseArgs();
  let chromium;
  try {
    ({ chromium } = await import('playwright-core'));
  } catch (e) {
    fatal('playwright-core is not installed: run `npm ci --prefix tests/browser` (scripts/test.sh does). ' + e.message);
  }
  if (!fs.existsSync(args.chromium)) fatal(`no browser at ${args.chromium}: install Debian's chromium (scripts/install-deps.sh)`);
  if (!fs.existsSync(args.oxbow)) fatal(`no oxbow binary at ${args.oxbow}`);
  for (const name of [...INDEXED, 'box.png']) {
    if (!fs.existsSync(path.join(SAMPLES, name))) fatal(`sample photo ${name} missing: install opencv-doc`);
  }
  fs.mkdirSync(args.artifacts, { recursive: true });
  fs.rmSync(path.join(args.artifacts, 'failure.png'), { force: true });  // a previous run's
  fs.mkdirSync(args.work, { recursive: true });

  // A small index: a 2048-word vocabulary trained on the indexed photos themselves (seconds; coarser
  // vocabularies leave too few words with few features each for re-ranking through shared words).
  const list = path.join(args.work, 'images.txt');
  fs.writeFileSync(list, INDEXED.map((n) => path.join(SAMPLES, n)).join('\n') + '\n');
  const vocab = path.join(args.work, 'vocab.oxvoc');
  const indexDir = path.join(args.work, 'index');
  fs.rmSync(indexDir, { recursive: true, force: true });
  const quiet = { stdio: ['ignore', 'ignore', 'pipe'] };
  execFileSync(args.oxbow, ['vocab', 'train', '--list', list, '--words', '2048', '--per-image', '1000',
                            '--out', vocab], quiet);
  execFileSync(args.oxbow, ['index', 'build', '--vocab', vocab, '--list', list, '--out', indexDir], quiet);
  // A truncated JPEG (the first half of a real one): the server must refuse it with a clear error.
  const truncated = path.join(args.work, 'truncated.jpg');
  const jpeg = fs.readFileSync(path.join(SAMPLES, 'leuvenA.jpg'));
  fs.writeFileSync(truncated, jpeg.subarray(0, Math.floor(jpeg.length / 2)));

  // A data folder of two collections put there by hand (so public, without limits): `default`, a copy of
  // the index, and `leuven`, three photos over the same vocabulary.
  const dataDir = path.join(args.work, 'data');
  fs.rmSync(dataDir, { recursive: true, force: true });
  fs.mkdirSync(dataDir, { recursive: true });
  fs.cpSync(indexDir, path.join(dataDir, 'default'), { recursive: true });
  const leuvenList = path.join(args.work, 'leuven.txt');
  fs.writeFileSync(leuvenList, LEUVEN.map((n) => path.join(SAMPLES, n)).join('\n') + '\n');
  execFileSync(args.oxbow, ['index', 'build', '--vocab', vocab, '--list', leuvenList, '--out', path.join(dataDir, 'leuven')], quiet);

  const { child, url } = await startServer(args.oxbow, ['--index', indexDir], path.join(args.work, 'serve.log'));
  let data = null;  // the server of the data folder (step 9)
  const browser = await chromium.launch({ executablePath: args.chromium, headless: true,
                                          args: ['--no-sandbox', '--disable-dev-shm-usage'] });
  const shot = async (page, name) => {
    const file = path.join(args.artifacts, name);
    await page.screenshot({ path: file, fullPage: true });
    console.log(`     screenshot ${file}`);
  };
  let page;
  try {
    await waitReady(url);
    const context = await browser.newContext({ viewport: { width: 1280, height: 900 } });
    context.setDefaultTimeout(60000);  // generous: ctest runs other suites beside this one on few cores
    page = await context.newPage();
    const consoleErrors = [];
    page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(`${m.text()} ${m.location().url || ''}`); });
    page.on('pageerror', (e) => consoleErrors.push(e.message));
    page.on('dialog', (d) => d.accept());  // the delete confirmation

    await page.goto(url + '/');
    await page.waitForSelector('body[data-ready="true"]');
    await page.waitForFunction(() => /\d+ images/.test(document.getElementById('status').textContent));
    check(/\b8 images\b/.test(await page.textContent('#status')), 'status strip shows the 8 indexed images');

    // 1. Upload box.png: box_in_scene first, with its matched region drawn on the thumbnail.
    await page.setInputFiles('#query-file', path.join(SAMPLES, 'box.png'));
    await page.waitForSelector('#results li');
    const first = await page.$eval('#results li', (li) => ({
      id: li.dataset.id, rank: li.dataset.rank, text: li.textContent,
      region: (() => { const r = li.querySelector('svg.overlay rect.region');
                       return r ? [r.getAttribute('width'), r.getAttribute('height')].map(Number) : null; })(),
    }));
    check(first.id === 'box_in_scene' && first.rank === '1', `rank 1 is box_in_scene (got ${first.id})`);
    check(first.region !== null && first.region[0] > 10 && first.region[1] > 10,
          `its matched region is drawn on the thumbnail (${first.region})`);
    check(/verified, \d+ inliers/.test(first.text), 'its caption says verified with the inlier count');
    await page.waitForFunction(() => [...document.querySelectorAll('#results img')].every((i) => i.complete && i.naturalWidth > 0));
    check(/last search: .*total \d+ ms/.test(await page.textContent('#status')), 'status strip shows the last search timings');
    await shot(page, 'results.png');

    // 2. The match view, opened from the keyboard: Tab from the last form field reaches the first result.
    await page.focus('#top-k');
    let reached = false;
    for (let i = 0; i < 10 && !reached; i++) {
      await page.keyboard.press('Tab');
      reached = await page.evaluate(() => document.activeElement?.closest('#results li')?.dataset.rank === '1');
    }
    check(reached, 'Tab reaches the first result');
    await page.keyboard.press('Enter');
    await page.waitForSelector('#match-svg line.corr', { state: 'attached' });
    const lines = await page.$$eval('#match-svg line.corr', (l) => l.length);
    check(lines >= 6, `match view draws the verified correspondences (${lines} lines)`);
    check(await linesInTheirPictures(page), 'every line runs from the query picture to the result picture');
    const details = await page.textContent('#match-details');
    check(/Transform/.test(details) && /scale \d/.test(details), 'match view shows the transform');
    await page.$eval('#match-view', (el) => el.scrollIntoView());
    await shot(page, 'match.png');

    // 3. Draw a query box with the mouse and search in it: the request carries bbox.
    const overlay = await page.$('#query-overlay');
    await overlay.scrollIntoViewIfNeeded();
    const b = await overlay.boundingBox();
    await page.mouse.move(b.x + b.width * 0.1, b.y + b.height * 0.1);
    await page.mouse.down();
    await page.mouse.move(b.x + b.width * 0.5, b.y + b.height * 0.5, { steps: 5 });
    await page.mouse.move(b.x + b.width * 0.9, b.y + b.height * 0.9, { steps: 5 });
    await page.mouse.up();
    check(await page.isVisible('#query-box'), 'the drawn box is shown on the query');
    const [request] = await Promise.all([
      page.waitForRequest((r) => r.url().includes('/v1/search')),
      page.click('#search-box-button'),
    ]);
    const bbox = new URL(request.url()).searchParams.get('bbox');
    check(bbox !== null && bbox.split(',').length === 4, `the search request had bbox=${bbox}`);
    await page.waitForFunction(() => /\(box [\d.]+/.test(document.getElementById('results-summary').textContent));
    check((await page.$eval('#results li', (li) => li.dataset.id)) === 'box_in_scene', 'box search: box_in_scene still first');
    // The keyboard moves the box too.
    const before = await page.textContent('#box-text');
    await page.focus('#query-overlay');
    await page.keyboard.press('ArrowLeft');
    check((await page.textContent('#box-text')) !== before, 'arrow keys move the box');
    await shot(page, 'box-search.png');

    // 4. Drag and drop a photo onto the drop zone.
    const boxBase64 = fs.readFileSync(path.join(SAMPLES, 'box.png')).toString('base64');
    await page.evaluate((data) => {
      const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
      const transfer = new DataTransfer();
      transfer.items.add(new File([bytes], 'dropped-box.png', { type: 'image/png' }));
      document.getElementById('drop-zone').dispatchEvent(new DragEvent('drop', { dataTransfer: transfer, bubbles: true, cancelable: true }));
    }, boxBase64);
    await page.waitForFunction(() => /No box/.test(document.getElementById('box-text').textContent) &&
                                     !/\(box /.test(document.getElementById('results-summary').textContent) &&
                                     document.querySelector('#results li'));
    check((await page.$eval('#results li', (li) => li.dataset.id)) === 'box_in_scene', 'a dropped photo is searched');

    // 5. Search by a pasted address of an indexed image, then its match view (the query is a thumbnail).
    await page.fill('#query-id', `${url}/v1/images/graf1/thumbnail`);
    await page.click('#search-id-button');
    await page.waitForFunction(() => document.querySelector('#results li')?.dataset.id === 'graf1');
    check(true, 'search by pasted address: graf1 finds itself first');
    await page.click('#results li:first-child button');
    await page.waitForSelector('#match-svg line.corr', { state: 'attached' });
    check(await linesInTheirPictures(page), 'by-id match view: every line runs between the two pictures');
    await shot(page, 'match-by-id.png');

    // 6. A truncated JPEG gives the error message.
    await page.setInputFiles('#query-file', truncated);
    await page.waitForSelector('#messages .error');
    const error = await page.textContent('#messages .error');
    check(/not a readable image/.test(error) && /HTTP 400 invalid_image/.test(error), `truncated file: "${error}"`);
    await shot(page, 'error.png');
    // A 68-byte PNG declaring 60000 x 60000 pixels: refused from its header (413), with its own message.
    await page.setInputFiles('#query-file', { name: 'huge.png', mimeType: 'image/png', buffer: hugePng() });
    await page.waitForFunction(() => /too large/.test(document.querySelector('#messages .error')?.textContent || ''));
    const tooLarge = await page.textContent('#messages .error');
    check(/HTTP 413 image_too_large/.test(tooLarge), `oversized image: "${tooLarge}"`);

    // 7. The collection: add an image (the API key is asked for), see its stored thumbnail, delete it.
    await page.click('#tab-browse');
    await page.waitForSelector('#collection li');
    check((await page.$$('#collection li')).length === 8, 'collection lists the 8 images');
    await page.setInputFiles('#add-file', path.join(SAMPLES, 'box.png'));
    await page.fill('#add-id', 'uploaded-box');
    await page.click('#add-button');
    await page.waitForSelector('#key-dialog[open]');
    check(/needs an API key/.test(await page.textContent('#key-reason')), 'adding without a key asks for it');
    await page.fill('#key-input', API_KEY);
    await page.click('#key-ok');
    await page.waitForSelector('#collection li[data-id="uploaded-box"]');
    check(/Added uploaded-box/.test(await page.textContent('#messages')), 'the add is confirmed');
    await page.waitForFunction(() => {
      const img = document.querySelector('#collection li[data-id="uploaded-box"] img');
      return img && img.complete && img.naturalWidth > 0;
    });
    check(true, 'the uploaded image has a thumbnail (stored at add time)');
    await shot(page, 'collection.png');
    await page.click('#collection li[data-id="uploaded-box"] button.danger');
    await page.waitForFunction(() => /Deleted uploaded-box/.test(document.getElementById('messages').textContent));
    check((await page.$('#collection li[data-id="uploaded-box"]')) === null, 'the deleted image left the collection');
    // (A server without collections answers GET /v1/collections 404: the picker stays hidden.)
    check(consoleErrors.filter((e) => !/status of (400|401|413)/.test(e) && !/status of 404.*\/v1\/collections$/.test(e)).length === 0,
          `no script errors (${consoleErrors.join(' | ')})`);
    await context.close();

    // 8. A phone-sized screen: same search, no horizontal scrolling.
    const phone = await browser.newContext({ viewport: { width: 375, height: 812 }, deviceScaleFactor: 2, hasTouch: true });
    phone.setDefaultTimeout(60000);
    const small = await phone.newPage();
    await small.goto(url + '/');
    await small.waitForSelector('body[data-ready="true"]');
    await small.setInputFiles('#query-file', path.join(SAMPLES, 'box.png'));
    await small.waitForSelector('#results li');
    await small.waitForFunction(() => [...document.querySelectorAll('#results img')].every((i) => i.complete && i.naturalWidth > 0));
    const overflow = await small.evaluate(() => document.documentElement.scrollWidth - window.innerWidth);
    check(overflow <= 0, `phone width: no horizontal overflow (${overflow} px)`);
    await shot(small, 'phone.png');
    await phone.close();

    // 9. Collections: `oxbow serve --data` over the data folder. The picker lists what the key may read,
    //    and the chosen collection's routes (/v1/collections/{name}/...) serve every search, thumbnail,
    //    list and status request; "default" is served by the routes without a prefix.
    data = await startServer(args.oxbow, ['--data', dataDir], path.join(args.work, 'serve-data.log'));
    await waitReady(data.url);
    const made = await fetch(`${data.url}/v1/collections`, {
      method: 'POST', headers: { 'X-API-Key': API_KEY, 'Content-Type': 'application/json' },
      body: JSON.stringify({ name: 'private', vocabulary: { like: 'default' } }) });
    check(made.status === 201, `the admin key creates a private collection (HTTP ${made.status})`);
    const collections = await browser.newContext({ viewport: { width: 1280, height: 900 } });
    collections.setDefaultTimeout(60000);
    page = await collections.newPage();
    const pickerErrors = [];
    page.on('console', (m) => { if (m.type() === 'error') pickerErrors.push(`${m.text()} ${m.location().url || ''}`); });
    page.on('pageerror', (e) => pickerErrors.push(e.message));
    const requested = [];
    page.on('request', (r) => requested.push(new URL(r.url()).pathname));
    const options = () => page.$$eval('#collection-select option', (list) => list.map((o) => o.value).join(','));
    const statusShows = (n) => page.waitForFunction((k) => new RegExp(`\\b${k} images\\b`).test(document.getElementById('status').textContent), n);

    await page.goto(data.url + '/');
    await page.waitForSelector('body[data-ready="true"]');
    check(await page.isVisible('#collection-select'), 'the collection picker is shown');
    check(await page.$eval('#collection-select', (s) => [...s.labels].map((l) => l.textContent.trim()).join()) === 'Collection',
          'the picker is labelled "Collection"');
    check((await options()) === 'default,leuven', `without a key it lists the public collections (${await options()})`);
    check((await page.inputValue('#collection-select')) === 'default', 'default is chosen first');
    await statusShows(8);
    check(requested.includes('/v1/stats') && !requested.some((p) => /^\/v1\/collections\/default\//.test(p)),
          'default is served by the routes without a prefix');

    // Chosen from the keyboard: the status strip, searches, thumbnails and the images tab follow.
    await page.focus('#collection-select');
    await page.keyboard.press('ArrowDown');
    await statusShows(3);
    check((await page.inputValue('#collection-select')) === 'leuven', 'ArrowDown on the picker chooses leuven (3 images)');
    requested.length = 0;
    await page.setInputFiles('#query-file', path.join(SAMPLES, 'box.png'));
    await page.waitForSelector('#results li');
    await page.waitForFunction(() => [...document.querySelectorAll('#results img')].every((i) => i.complete && i.naturalWidth > 0));
    const found = await page.$$eval('#results li', (list) => list.map((li) => li.dataset.id));
    check(found[0] === 'box_in_scene' && found.every((id) => ['leuvenA', 'leuvenB', 'box_in_scene'].includes(id)),
          `the search found leuven's images only, box_in_scene first (${found})`);
    check(requested.includes('/v1/collections/leuven/search') && !requested.includes('/v1/search'),
          'the search went to /v1/collections/leuven/search');
    const pictures = await page.$$eval('#results img', (list) => list.map((i) => new URL(i.src).pathname));
    check(pictures.length > 0 && pictures.every((p) => /^\/v1\/collections\/leuven\/images\/[^/]+\/thumbnail$/.test(p)),
          `the thumbnails are leuven's (${pictures[0]})`);
    await shot(page, 'collections.png');
    await page.fill('#query-id', 'leuvenA');
    await page.click('#search-id-button');
    await page.waitForFunction(() => document.querySelector('#results li')?.dataset.id === 'leuvenA');
    check(requested.includes('/v1/collections/leuven/images/leuvenA') &&
          requested.includes('/v1/collections/leuven/images/leuvenA/similar'), 'a search by id asks leuven');
    await page.click('#tab-browse');
    await page.waitForFunction(() => document.querySelectorAll('#collection li').length === 3);
    check(requested.includes('/v1/collections/leuven/images'), 'the images tab lists leuven');

    // The choice is kept for the tab; a new key reads the list again.
    await page.reload();
    await page.waitForSelector('body[data-ready="true"]');
    check((await page.inputValue('#collection-select')) === 'leuven', 'a reload keeps leuven chosen');
    await statusShows(3);
    await page.click('#key-button');
    await page.waitForSelector('#key-dialog[open]');
    await page.fill('#key-input', API_KEY);
    await page.click('#key-ok');
    await page.waitForFunction(() => [...document.querySelectorAll('#collection-select option')].some((o) => o.value === 'private'));
    check((await options()) === 'default,leuven,private', `with the admin key it lists every collection (${await options()})`);
    check((await page.inputValue('#collection-select')) === 'leuven', 'the new key keeps leuven chosen');

    // Back to default: the photo is searched again, through /v1/search.
    await page.click('#tab-search');
    await page.setInputFiles('#query-file', path.join(SAMPLES, 'box.png'));
    await page.waitForSelector('#results li');
    requested.length = 0;
    await Promise.all([page.waitForRequest((r) => new URL(r.url()).pathname === '/v1/search'),
                       page.selectOption('#collection-select', 'default')]);
    await page.waitForSelector('#results li');
    await statusShows(8);
    check(!requested.some((p) => p.startsWith('/v1/collections/')), 'default: no request under /v1/collections/');
    const metrics = await (await fetch(`${data.url}/metrics`)).text();
    check(/^oxbow_http_requests_total\{.*collection="leuven".*\} \d/m.test(metrics), 'the request metrics carry collection="leuven"');
    check(pickerErrors.length === 0, `no script errors with collections (${pickerErrors.join(' | ')})`);

    // A server without collections answers GET /v1/collections 404: no picker, the routes of /v1.
    const older = await collections.newPage();
    await older.route('**/v1/collections', (route) => route.fulfill({
      status: 404, contentType: 'application/json',
      body: JSON.stringify({ error: { code: 'not_found', message: 'no route', request_id: 'test' } }) }));
    await older.goto(data.url + '/');
    await older.waitForSelector('body[data-ready="true"]');
    await older.waitForFunction(() => /\b8 images\b/.test(document.getElementById('status').textContent));
    check(!(await older.isVisible('#collection-select')), 'GET /v1/collections 404: the picker stays hidden');
    await collections.close();
  } catch (e) {
    failures++;
    console.error('FAIL', e.stack || e.message);
    if (page && !page.isClosed()) await shot(page, 'failure.png').catch(() => {});
  } finally {
    await browser.close();
    child.kill('SIGTERM');
    if (data) data.child.kill('SIGTERM');
  }
  console.log(failures === 0 ? 'search_page.test: all checks passed' : `search_page.test: ${failures} check(s) failed`);
  process.exit(failures === 0 ? 0 : 1);
}

main().catch((e) => fatal(e.stack || e.message));
