// Build: `npm run build` -> dist/ (served by the API at /). Dev: `npm run dev` proxies /v1 to the service.
import { defineConfig } from 'vite';

const api = process.env.RETARGET_API_URL || 'http://127.0.0.1:8000';

export default defineConfig({
  base: '/',
  build: {
    outDir: 'dist',
    emptyOutDir: true,
    target: 'es2022',
    chunkSizeWarningLimit: 1600, // three.js and the glTF validator are big; the validator loads on demand
    rollupOptions: {
      output: { manualChunks: { three: ['three'] } },
    },
  },
  server: {
    proxy: { '/v1': api, '/openapi.json': api, '/docs': api, '/healthz': api, '/readyz': api },
  },
});
