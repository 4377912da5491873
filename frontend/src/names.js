/** Display names of motions and characters by id (cached; the job rows only carry ids). */
import { api, listAll } from './api.js';

const cache = new Map();

/** Remember assets seen elsewhere (upload answers, lists). */
export function rememberAsset(asset) {
  if (asset && asset.id) cache.set(asset.id, asset);
}

/** The cached asset of an id, or undefined. */
export function assetOf(id) {
  return cache.get(id);
}

/** A name for an id: the asset's name, or the id itself. */
export function nameOf(id) {
  return cache.get(id)?.name ?? id;
}

let listed = null;

/** Make sure the given ids are known (one list call per collection, then single gets for stragglers). */
export async function loadNames(motionIds = [], characterIds = []) {
  const missing = () => [...motionIds, ...characterIds].filter((id) => id && !cache.has(id));
  if (missing().length && !listed) {
    listed = Promise.all([listAll('/v1/motions', 1000), listAll('/v1/characters', 1000)])
      .then(([m, c]) => { for (const a of [...m, ...c]) rememberAsset(a); })
      .catch(() => {})
      .finally(() => { setTimeout(() => { listed = null; }, 5000); });
  }
  if (listed) await listed;
  await Promise.all(missing().slice(0, 20).map((id) => {
    const coll = motionIds.includes(id) ? 'motions' : 'characters';
    return api(`/v1/${coll}/${encodeURIComponent(id)}`).then(rememberAsset).catch(() => {});
  }));
  return { nameOf };
}
